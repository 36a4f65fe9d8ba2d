"""Applications of the localizer: what the tools run on top of the core.

Problem assembly from a configuration (``problem.py``), photo lists and poses files of batches
(``inputs.py``), result files (``output.py``), the resumable record of a batch (``ledger.py``),
batches over worker processes (``batch``), video tracking (``tracking.py``) and the built-in demo
scene (``demo_scene.py``). The core (rasterizer, pose, io, matchers, localization) never imports
this package (tests/test_layering.py).
"""
