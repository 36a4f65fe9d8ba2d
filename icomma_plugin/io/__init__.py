"""Files: one place for every format the project reads or writes.

3DGS model folders (``model_folder``), Gaussian PLY (``ply``), ``cameras.json``
(``cameras_json``), datasets (``datasets``: COLMAP, Blender, LLFF, transforms.json), poses files
(``poses_file``), exports of estimated poses (``export``), videos and GIFs (``video``), and
atomic writes and file locks (``atomic``).
"""
