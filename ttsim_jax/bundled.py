"""Where the files shipped with the package are (a light module: the CLI reads its defaults from
them before JAX is imported)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def config_dir() -> Path:
    """The folder of the bundled configs (``models/*.toml``, ``residual/*.toml``).

    Returns:
        ``ttsim_jax/configs`` of an installed wheel (found with :mod:`importlib.resources`), else,
        in a source checkout or an editable install, the checkout's top-level ``configs/``: the
        wheel is built from that folder, so both hold the same files.
    """
    packaged = resources.files("ttsim_jax") / "configs"
    if packaged.is_dir():
        return Path(str(packaged))
    return Path(__file__).resolve().parents[1] / "configs"
