"""icomma_plugin: camera pose estimation by inverting a trained 3D Gaussian Splatting model.

Conventions (frames, se(3) order, pixel centres) are fixed in docs/CONTRACTS.md.
"""
