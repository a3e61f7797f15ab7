"""One-line errors for every command of the package (``pe-rlhf`` and the recipe scripts).

A bad value or argument prints ``error: <message>`` to stderr and exits 2, without a traceback;
``PE_RLHF_DEBUG=1`` (or ``pe-rlhf --debug``) shows the traceback instead. Standard library only, so the
command line starts fast and every layer may use it.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import NoReturn

DEBUG_ENV_VAR = "PE_RLHF_DEBUG"


def debug_requested() -> bool:
    """Whether ``$PE_RLHF_DEBUG`` asks for tracebacks (set, and not ``0``)."""
    return os.environ.get(DEBUG_ENV_VAR, "") not in ("", "0")


def fail(message: str) -> NoReturn:
    """Print ``error: <message>`` to stderr as one line and exit 2 (a usage error)."""
    print("error: " + " ".join(line.strip() for line in str(message).splitlines()), file=sys.stderr)
    raise SystemExit(2)


class OneLineErrorParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors (a bad argument, or a ``parser.error`` on a bad value) are one line:
    :func:`fail`. With ``debug`` set (or ``$PE_RLHF_DEBUG``), an error raised while handling an exception
    re-raises that exception, so its traceback shows."""

    debug = False

    def error(self, message: str) -> NoReturn:
        handled = sys.exception()
        if (self.debug or debug_requested()) and handled is not None \
                and not isinstance(handled, argparse.ArgumentError):
            raise handled
        fail(message)


__all__ = ["DEBUG_ENV_VAR", "OneLineErrorParser", "debug_requested", "fail"]
