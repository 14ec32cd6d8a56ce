"""The errors a user's input can cause: their base class, and those raised in more than one layer."""


class UserError(Exception):
    """Base of every error a user's input can cause; the CLI prints it as one ``error:`` line.

    Each library error of this kind (a bad config, dataset, checkpoint, size, ...) derives from it
    and, where it has one, from its former base too (``class ConfigError(UserError, ValueError)``),
    so that ``except ValueError`` keeps catching it. Its message names the file, key or value.
    """


class ConfigError(UserError, ValueError):
    """A configuration (a model, task, residual network or training file) with a missing, unknown or
    invalid key or value; the message names the file, the key and the value."""
