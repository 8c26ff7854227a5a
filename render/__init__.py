"""Render: cameras, meshes, UV binding, the Gaussian rasterizer and RGCA shading."""
