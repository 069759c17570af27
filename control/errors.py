"""Typed errors.

Every error a user can cause with a bad file or a bad argument is a :class:`PneutuneError`.
The command-line entry points turn it into one ``error: ...`` line on stderr and exit status 2
(see :func:`pneutune.control.cli.common.run_cli`). Each also subclasses a builtin so that library
users can catch it as the builtin they expect.
"""

from __future__ import annotations


class PneutuneError(Exception):
    """Base of all user-facing errors (bad input, not a bug).

    Attributes
    ----------
    argument, flag : str or None
        Set by :func:`argument_error`: the library argument and the command flag at fault.
    rule : str
        The rule broken and the value, without the argument's name.
    """

    argument: str | None = None
    flag: str | None = None
    rule: str = ""


class ConfigError(PneutuneError, ValueError):
    """A YAML configuration file is invalid.

    Parameters
    ----------
    file : str
        The file (or ``"<defaults>"``) the value came from.
    key : str
        Dotted key path, e.g. ``valves.a_in.C``; empty when the whole file is wrong.
    message : str
        The rule that was broken and the value that broke it.
    """

    def __init__(self, file: str, key: str, message: str) -> None:
        self.file = str(file)
        self.key = key
        self.message = message
        where = f"{self.file}: {key}: " if key else f"{self.file}: "
        super().__init__(where + message)


class LogError(PneutuneError, ValueError):
    """A run log (MCAP, contract 1) cannot be used.

    Parameters
    ----------
    file : str
        Path of the log.
    message : str
        What is wrong and, where known, the record (topic, log time) that is wrong.
    """

    def __init__(self, file: str, message: str) -> None:
        self.file = str(file)
        self.message = message
        super().__init__(f"{self.file}: {message}")


class NotMcapError(LogError):
    """The file is not an MCAP file (bad magic or unreadable header)."""


class TruncatedLogError(LogError):
    """The file is an MCAP file that was cut short or is internally corrupt."""


class EmptyLogError(LogError):
    """The file holds no messages."""


class MissingTopicError(LogError):
    """A required topic is absent."""


class NonFiniteValueError(LogError):
    """A numeric field holds NaN, an infinity or null."""


class TimeOrderError(LogError):
    """Log times of a topic go backwards."""


class MissingMetadataError(LogError):
    """The ``rig`` or ``run`` metadata record is missing or incomplete."""


class LogSchemaError(LogError):
    """A record of the log does not match contract 1.

    A channel of a contract topic is not JSON, a message lacks a field or has one its schema
    does not know, a value has the wrong type, a metadata record has an unknown key or another
    schema version.
    """


class ExperimentError(PneutuneError, ValueError):
    """An experiment or scenario cannot be run as requested."""


def argument_error(cls: type[PneutuneError], argument: str, rule: str,
                   flag: str | None = None) -> PneutuneError:
    """An error about one argument of a library call, worded for the library and the command.

    ``str()`` of the error names the Python argument (``mass_tol must be in [0, 1), got 2``);
    :func:`command_message` names the command's flag instead (``--mass-tol must be ...``), so
    the same check serves a notebook and the command line.

    Parameters
    ----------
    cls : type
        The error class (a :class:`PneutuneError` taking one message).
    argument : str
        The argument's Python name.
    rule : str
        The rule and the value that broke it, without the name.
    flag : str, optional
        The command's flag; default ``--`` and the argument with ``_`` as ``-``.

    Returns
    -------
    PneutuneError
        To raise.
    """
    exc = cls(f"{argument} {rule}")
    exc.argument = argument
    exc.flag = flag or "--" + argument.replace("_", "-")
    exc.rule = rule
    return exc


def command_message(exc: BaseException) -> str:
    """The error's message as a command prints it: an argument error names the flag."""
    if isinstance(exc, PneutuneError) and exc.flag:
        return f"{exc.flag} {exc.rule}"
    return str(exc)
