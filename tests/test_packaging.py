"""A regular (non-editable) install ships the EDS and the configs as data files; virtualaxis.resources finds them."""

import fnmatch
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from virtualaxis import resources

ROOT = Path(__file__).resolve().parents[1]


def test_every_shipped_file_is_listed_in_the_data_files():
    data_files = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["data-files"]
    patterns = [p for pats in data_files.values() for p in pats]
    shipped = [p.relative_to(ROOT).as_posix() for d in ("eds", "configs") for p in (ROOT / d).rglob("*")
               if p.is_file()]
    assert shipped
    missing = [f for f in shipped if not any(fnmatch.fnmatch(f, pat) and f.count("/") == pat.count("/")
                                             for pat in patterns)]
    assert not missing, f"not installed by a regular pip install: {missing}"


def test_project_file_falls_back_to_the_installed_data_files(tmp_path, monkeypatch):
    assert resources.project_file("eds/virtualaxis.eds") == ROOT / "eds" / "virtualaxis.eds"
    share = tmp_path / "share" / "virtualaxis"
    (share / "eds").mkdir(parents=True)
    (share / "eds" / "virtualaxis.eds").write_text("[FileInfo]\n")
    monkeypatch.setattr(resources, "_REPO_ROOT", tmp_path / "site-packages-parent")
    monkeypatch.setattr(resources, "_SHARE", share)
    assert resources.project_file("eds/virtualaxis.eds") == share / "eds" / "virtualaxis.eds"
    # neither: the repository path, so the error names where it was expected
    assert resources.project_file("eds/nope.eds") == tmp_path / "site-packages-parent" / "eds" / "nope.eds"
