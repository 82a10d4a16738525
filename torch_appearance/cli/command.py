"""What every ``ta-…`` command shares: a parser whose bad-input exit is one line, and the checks of output paths.

A command is a module of :mod:`torch_appearance.cli` with ``main(argv=None) -> int``; setup.cfg installs it as a
console script ``ta-<name>``. Bad input exits with status 2 and one line on stderr that names the argument, what was
wrong and how to fix it; nothing is written before the input has been checked.
"""
import argparse
import os
import sys

__all__ = ["CommandParser", "fail", "check_output_file", "check_output_folder"]


class CommandParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` for a ``ta-…`` command.

    The description is the first paragraph of ``doc`` and the epilog the rest (its ``Examples:`` block), printed
    verbatim by ``--help``. :meth:`error` prints one line and exits with status 2.

    Example:
        >>> p = CommandParser("ta-example", "Do a thing.\\n\\nExamples:\\n    ta-example --n 3")
        >>> p.add_argument("--n", type=int, default=1)  # doctest: +ELLIPSIS
        _StoreAction(...)
        >>> p.parse_args(["--n", "3"]).n
        3
    """

    def __init__(self, prog, doc, **kwargs):
        head, _, rest = doc.strip().partition("\n\n")
        super().__init__(prog=prog, description=head, epilog=rest or None,
                         formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def fail(prog, message):
    """Print ``prog: error: message`` on stderr and return the exit status 2 (``return fail(...)`` from ``main``)."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    return 2


def check_output_file(parser, flag, path):
    """Refuse (exit 2) an output file ``path`` that is an existing folder or whose folder does not exist."""
    if path is None:
        return
    if os.path.isdir(path):
        parser.error(f"{flag}: expected a file name, got the folder {path!r}; name a file inside it")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        parser.error(f"{flag}: the folder of {path!r} does not exist; create it first")


def check_output_folder(parser, flag, path):
    """Refuse (exit 2) an output folder ``path`` that exists as a file."""
    if path is not None and os.path.exists(path) and not os.path.isdir(path):
        parser.error(f"{flag}: expected a folder, got the existing file {path!r}; name a new or existing folder")
