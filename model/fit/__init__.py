"""Fitting unseen subjects: input views, the fitter, the avatar file and its tools, PLY export."""
