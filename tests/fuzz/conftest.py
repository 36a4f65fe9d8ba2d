"""Keep hypothesis's cache (example constants, unicode tables) out of the repository."""
import os
import tempfile

os.environ.setdefault("HYPOTHESIS_STORAGE_DIRECTORY",
                      os.path.join(tempfile.gettempdir(), "icomma-hypothesis"))
