"""The ``ttsim`` command line: :func:`main` runs ``ttsim ARGV`` (``python -m ttsim_jax.cli`` too).

:mod:`~ttsim_jax.cli.main` assembles the parser and reports errors, :mod:`~ttsim_jax.cli.options`
holds what the subcommands share (the options' validators, :class:`UsageError`), and each other
module is one subcommand (or one group of them): a thin wrapper that parses, calls the library and
prints. Parsing the arguments imports no JAX.
"""

from ttsim_jax.cli.main import build_parser, main
from ttsim_jax.cli.options import UsageError

__all__ = ["UsageError", "build_parser", "main"]
