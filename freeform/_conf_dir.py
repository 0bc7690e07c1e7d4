"""Where ``freeform-train``'s Hydra configs are: the one place that decides.

The YAML files live in the repository's top-level ``conf/``. A built wheel ships them as package data, mapped to
``freeform/conf`` (``pyproject.toml``: ``[tool.setuptools] package-dir``), so there are two places to look:

- installed from a wheel, an sdist or git (``pip install .``): ``<site-packages>/freeform/conf``;
- a source checkout, editable install (``make install``) included: ``<checkout>/conf``, read in place, so an
  edit to ``conf/`` takes effect without reinstalling.

The installed copy is looked for first: it belongs to this very package, whereas the directory beside the package
is only trusted when it is a checkout of freeform (it holds ``pyproject.toml``; in ``site-packages`` a top-level
``conf/`` would be another distribution's).
"""

from __future__ import annotations

from pathlib import Path

_PRIMARY = "config.yaml"  # Hydra's primary config, config_name="config"
_PACKAGE = Path(__file__).resolve().parent
_INSTALLED = _PACKAGE / "conf"
_CHECKOUT = _PACKAGE.parent / "conf"


def conf_dir() -> Path:
    """The directory holding ``config.yaml`` and the config groups: the installed package data, else the checkout's
    ``conf/``. Raises ``FileNotFoundError`` (saying where it looked) when neither has them."""
    if (_INSTALLED / _PRIMARY).is_file():
        return _INSTALLED
    if (_CHECKOUT / _PRIMARY).is_file() and (_PACKAGE.parent / "pyproject.toml").is_file():
        return _CHECKOUT
    raise FileNotFoundError(
        f"freeform's configs are missing: neither {_INSTALLED} (an installed freeform) nor {_CHECKOUT} (a source "
        f"checkout) holds {_PRIMARY}. Reinstall freeform (`pip install --force-reinstall <wheel or source>`, "
        "or `make install` in a checkout)."
    )


__all__ = ["conf_dir"]
