"""Where the project's own files are: the EDS and the shipped axis configs.

From a clone (editable install) they are the repository's ``eds/`` and ``configs/``; a regular install
(``pip install .``) ships them as data files under ``<prefix>/share/virtualaxis/``.
"""

from __future__ import annotations

import sys
from pathlib import Path

_REPO_ROOT = Path(__file__).resolve().parents[2]
_SHARE = Path(sys.prefix) / "share" / "virtualaxis"


def project_file(relative: str) -> Path:
    """``relative`` (e.g. ``"eds/virtualaxis.eds"``) in the repository, else in the installed data files.
    Returns the repository path when neither exists (so an error names the expected place)."""
    for root in (_REPO_ROOT, _SHARE):
        p = root / relative
        if p.exists():
            return p
    return _REPO_ROOT / relative
