"""The stages of a localization and what they share (docs/LOCALIZATION.md).

``icomma_plugin.localize.localize`` composes them: the default method (``robust.py``) and the
paper's (``icomma.py``), over one ``LocalizationState`` (``state.py``); batches, sequences and
their records are ``batch.py``, ``tracking.py`` and ``ledger.py``.
"""
