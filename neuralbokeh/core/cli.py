"""What every command-line entry point of the package shares (the CLIs import this; the library never
imports the CLIs).

A user's mistake (a missing or unreadable file, a bad value, a file that is not what it should
be) ends the command with one ``error: ...`` line on stderr and exit status 2, the status
argparse uses for a bad command line; ``-v`` / ``--verbose`` shows the traceback as well.
Anything else is a bug and keeps its traceback. Ctrl-C ends with status 130 and one line.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import traceback
from collections.abc import Callable, Sequence

# What a user's input can cause: files (OSError covers missing, unreadable, a directory), values
# (ValueError: every check of the package raises it), files that are not checkpoints (pickle).
USER_ERRORS = (OSError, ValueError, pickle.UnpicklingError, EOFError)
EXIT_USAGE = 2


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """The description as written, and each option's default after its help, where it has one
    that says something (not for required options, flags or ``None``) and the help does not
    already state it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (action.required or default in (None, False, argparse.SUPPRESS) or "default" in text.lower()
                or not action.option_strings or isinstance(default, list) and not default):
            return text
        shown = " ".join(map(str, default)) if isinstance(default, (list, tuple)) else default
        return f"{text} (default: {shown})"


def run_cli(main: Callable[[list[str] | None], int], argv: Sequence[str] | None = None) -> int:
    """Run ``main(argv)`` and turn a user's mistake into one ``error:`` line and exit status 2.

    ``main`` may also raise ``SystemExit("error: ...")`` for a mistake it finds itself.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    verbose = any(a in ("-v", "--verbose") for a in args)
    try:
        return main(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except SystemExit as e:
        if isinstance(e.code, str):
            if verbose:
                traceback.print_exc()
            print(e.code if e.code.startswith("error:") else f"error: {e.code}", file=sys.stderr)
            return EXIT_USAGE
        raise
    except USER_ERRORS as e:
        if verbose:
            traceback.print_exc()
        print(f"error: {_one_line(e)}", file=sys.stderr)
        return EXIT_USAGE


def _one_line(e: BaseException) -> str:
    text = str(e) or type(e).__name__
    if isinstance(e, OSError) and e.filename and str(e.filename) not in text:
        text = f"{text}: {e.filename}"
    return " ".join(text.split())
