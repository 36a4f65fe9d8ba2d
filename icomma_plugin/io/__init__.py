"""File formats: 3DGS model folders, PLY, cameras.json, datasets. One place for every format."""
