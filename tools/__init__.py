"""The command-line tools: the only importers of Hydra, and the entry points of icomma.

In a checkout they run as scripts (``python tools/localize.py``); an install (``pip install
--no-build-isolation .``) ships this folder as the package ``icomma_tools`` with the Hydra configs
inside it, and the commands ``icomma-localize``, ``icomma-benchmark``, ``icomma-fit`` and
``icomma-bench`` call each tool's ``main``.
"""
