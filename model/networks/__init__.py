"""The networks: decoders, Gaussians from UV maps, the stage-1 model, the stage-2 UNet, the single-stage baseline, presets."""
