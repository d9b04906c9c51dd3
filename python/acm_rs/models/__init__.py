"""The ACM paper's rodent models (Monsees et al. 2022, Supp. Fig. 1, Supp. Tables 1-2, sec. 6).

The models are TOML data files beside this module (``rat.toml``, ``mouse.toml``); see
``docs/skeleton_format.md`` for the format and ``docs/models.md`` for the choices made.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from ..skeleton import Skeleton

__all__ = ["available", "load", "load_name_or_file", "mouse", "path", "rat"]


def available() -> list[str]:
    """Names of the bundled models."""
    return sorted(
        p.name[: -len(".toml")]
        for p in resources.files(__name__).iterdir()
        if p.name.endswith(".toml")
    )


def path(name: str) -> Path:
    """Path of a bundled model file."""
    if name not in available():
        raise ValueError(f"unknown model {name!r}; available: {available()}")
    return Path(str(resources.files(__name__).joinpath(f"{name}.toml")))


def load(name: str) -> Skeleton:
    """Load a bundled model by name (``"rat"`` or ``"mouse"``)."""
    return Skeleton.load(path(name))


def load_name_or_file(spec: str | Path) -> Skeleton:
    """A bundled model by name, else a skeleton TOML file by path.

    What ``--model`` / ``--skeleton`` of the command line and ``project.model`` of a project's
    ``config.toml`` accept.
    """
    if spec in available():
        return load(str(spec))
    if Path(spec).exists():
        return Skeleton.load(spec)
    raise ValueError(f"--model {str(spec)!r} is neither a bundled model {available()} nor a file")


def rat() -> Skeleton:
    """The ACM rat model: 29 joints, 28 bones, 43 markers, 50 free pose entries (cm)."""
    return load("rat")


def mouse() -> Skeleton:
    """The ACM mouse model (rat topology, mouse bone lengths of Supp. Table 2; cm)."""
    return load("mouse")
