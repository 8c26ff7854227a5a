"""Model: stage 1 (full-on Gaussians), stage 2 (relighting), fitting."""
