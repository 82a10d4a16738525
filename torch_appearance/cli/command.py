"""What every ``ta-…`` command shares: a parser whose bad-input exit is one line, and the checks of output paths.

A command is a module of :mod:`torch_appearance.cli` with ``main(argv=None) -> int``; setup.cfg installs it as a
console script ``ta-<name>``. Bad input exits with status 2 and one line on stderr that names the argument, what was
wrong and how to fix it; nothing is written before the input has been checked, and an output that cannot be
written is refused before any work. The library keeps its own argument names (``width_mm: expected > 0``); a command
translates them into its flags in one place (:func:`flag_names`, :func:`in_flags`, ``fail(..., flags=...)``).
Ctrl-C ends a command with one line and the exit status 130 (:data:`INTERRUPTED`, :func:`interrupted`).
"""
import argparse
import contextlib
import os
import re
import sys
import tempfile

from ..interrupts import folder_listing, sigint_deferred, undo_partial  # noqa: F401  (part of this API)

__all__ = ["CommandParser", "fail", "interrupted", "flag_names", "in_flags", "check_output_file",
           "check_output_folder", "folder_listing", "undo_partial", "owned_folder", "interrupted_message",
           "add_device_argument", "resolve_device", "REFUSED", "INTERRUPTED"]

#: exit status of refused input (one line on stderr), as argparse's
REFUSED = 2
#: exit status after Ctrl-C (128 + SIGINT), as a shell reports a command ended by it
INTERRUPTED = 130


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
        """Exit with status 2 and one line: argparse's ``argument --x: --x: ...`` (a type's own message naming its
        flag) reads ``--x: ...``."""
        message = _one_prefix(re.sub(r"^argument ([^:]+): ", r"\1: ", str(message)))
        self.exit(REFUSED, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def add_device_argument(parser):
    """``--device auto|cpu|cuda[:N]``: where the tracer runs (:func:`resolve_device` turns it into a device)."""
    parser.add_argument("--device", default="auto", metavar="auto|cpu|cuda[:N]",
                        help="where the tracer runs: auto (a CUDA GPU when torch sees one that can render, else the "
                             "CPU), cpu, cuda or cuda:N (default: %(default)s)")


def resolve_device(parser, value, log=None):
    """The ``torch.device`` of a ``--device`` value; bad or unusable values exit through ``parser.error`` (one line).

    ``auto`` takes ``cuda`` when torch sees a GPU that can render (:func:`torch_appearance.render.cuda_launch.
    cuda_unavailable` is None), else the CPU; ``log`` (a callable) receives one line saying which and why.

    Example:
        >>> str(resolve_device(CommandParser("ta-x", "X."), "cpu"))
        'cpu'
    """
    import torch

    from ..render.cuda_launch import cuda_unavailable, device_unusable

    text = str(value).strip().lower()
    if text == "auto":
        missing = cuda_unavailable()
        device = torch.device("cpu") if missing else torch.device("cuda", torch.cuda.current_device())
        if log is not None:
            log(f"device: {device} (--device auto: " + (f"{missing})" if missing else
                                                         f"{torch.cuda.get_device_name(device)})"))
        return device
    if text == "cpu":
        if log is not None:
            log("device: cpu")
        return torch.device("cpu")
    if re.fullmatch(r"cuda(?::\d+)?", text) is None:
        parser.error(f"--device: expected auto, cpu, cuda or cuda:N, got {value!r}")
    why = device_unusable(text)
    if why:
        parser.error(f"--device: {why}; use --device cpu or auto")
    index = torch.device(text).index
    index = torch.cuda.current_device() if index is None else index
    device = torch.device("cuda", index)
    if log is not None:
        log(f"device: {device} ({torch.cuda.get_device_name(device)})")
    return device


def fail(prog, message, flags=None, values=None):
    """Print ``prog: error: message`` on stderr and return the exit status 2 (``return fail(...)`` from ``main``).

    With ``flags`` (:func:`flag_names`) the message, a library's, is put in the command's words first
    (:func:`in_flags`, ``values`` as there)."""
    message = str(message)
    if flags is not None:
        message = in_flags(message, flags, values)
    print(f"{prog}: error: {message}", file=sys.stderr)
    return REFUSED


def interrupted(prog, message):
    """Print ``prog: interrupted; message`` (what was kept and what to do) on stderr and return the exit status 130
    (``except KeyboardInterrupt: return interrupted(...)`` from ``main``)."""
    print(f"{prog}: interrupted; {message}", file=sys.stderr)
    return INTERRUPTED


@contextlib.contextmanager
def owned_folder(prog, folder, what, flag="--out"):
    """The run folder ``folder`` held by the command ``prog`` while the ``with`` block writes it
    (:func:`~torch_appearance.pipelines.runs.claim_run_folder`: another tool's folder, or one that another process
    holds, is refused with a ValueError naming ``flag``; the folder is locked and marked as ``prog``'s). After Ctrl-C
    in the block what it wrote is undone under the lock (:func:`undo_partial`, ``what`` e.g. "fit") and the
    ``KeyboardInterrupt`` raised again with what was kept as its message, for :func:`interrupted`."""
    from ..pipelines.runs import claim_run_folder  # here: the ring commands import this module without the pipelines

    before = folder_listing(folder)
    with claim_run_folder(folder, prog, flag):
        try:
            yield
        except KeyboardInterrupt:
            with sigint_deferred():  # a second Ctrl-C does not cut the undo in two
                kept = undo_partial(folder, before, what)
            raise KeyboardInterrupt(kept) from None


def interrupted_message(stop):
    """What a ``KeyboardInterrupt`` raised by :func:`owned_folder` says was kept; one raised elsewhere (while the
    folder was claimed, before anything was written in it) says nothing was written."""
    return str(stop) or "nothing was written (start it again)"


def flag_names(parser, **aliases):
    """The library's argument names as this command's flags: every destination of ``parser`` by its first option
    string (``width_mm`` -> ``--width-mm``; a positional keeps its name), and ``aliases`` for the library's names
    that no destination has (``names="--inks"``: the ink loader's argument).

    Example:
        >>> p = CommandParser("ta-example", "Do a thing.")
        >>> _ = p.add_argument("--width-mm", type=float)
        >>> flag_names(p, names="--inks")["width_mm"], flag_names(p, names="--inks")["names"]
        ('--width-mm', '--inks')
    """
    flags = {}
    for action in parser._actions:
        if action.dest in (argparse.SUPPRESS, "help"):
            continue
        flags[action.dest] = action.option_strings[0] if action.option_strings else action.dest
    flags.update(aliases)
    return flags


_LEADING = re.compile(r"^([A-Za-z_][\w]*(?:\[\d+\])?(?:/[A-Za-z_][\w]*)*): ")


def in_flags(message, flags, values=None):
    """A library message in a command's words.

    ``flags`` maps the library's argument names to the command's flags (:func:`flag_names`). Translated: the
    leading argument name (``width_mm: ...``, ``names[1]: ...``, ``width_mm/height_mm: ...``); a leading name that
    no flag has (a loader's ``path: no such file 'x.obj'``) is the flag whose value in ``values`` (a dict, e.g.
    ``vars(args)``) the message quotes; ``name=True (--flag)`` and ``name=VALUE`` advice (``pass --resume``,
    ``pass --texture PATH``); other argument names with an underscore (``pass width_mm/height_mm``); then a flag
    named twice in a row (``--envmap: envmap: ...``) or again in brackets after it is named once.

    Example:
        >>> flags = {"width_mm": "--width-mm", "height_mm": "--height-mm", "resume": "--resume", "names": "--inks",
        ...          "mesh": "--mesh", "texture": "--texture"}
        >>> in_flags("width_mm/height_mm: too small", flags)
        '--width-mm/--height-mm: too small'
        >>> in_flags("names[1]: unknown ink 'foo'", flags)
        "--inks: unknown ink 'foo'"
        >>> in_flags("path: no such file 'cow.obj'", flags, {"mesh": "cow.obj"})
        "--mesh: no such file 'cow.obj'"
        >>> in_flags("out: 'r' holds a run; pass resume=True (--resume) to continue it", flags)
        "out: 'r' holds a run; pass --resume to continue it"
        >>> in_flags("hint: the mesh has no texture: pass texture=PATH (the image)", flags)
        'hint: the mesh has no texture: pass --texture PATH (the image)'
        >>> in_flags("height_mm: an object needs its height in mm (--height-mm)", flags)
        '--height-mm: an object needs its height in mm'
    """
    message = str(message)
    match = _LEADING.match(message)
    if match:
        names = [re.sub(r"\[\d+\]$", "", name) for name in match.group(1).split("/")]
        rest = message[match.end():]
        if all(name in flags for name in names):
            message = "/".join(flags[name] for name in names) + ": " + rest
        elif len(names) == 1 and values:
            quoted = [flags.get(dest, dest) for dest, value in values.items()
                      if isinstance(value, str) and value and repr(value) in rest and dest in flags]
            if len(quoted) == 1:
                message = f"{quoted[0]}: {rest}"
    message = re.sub(r"\b([a-z_]+)=True \((--[\w-]+)\)", r"\2", message)
    message = re.sub(r"\b([a-z_]+)=([A-Z]+)\b",
                     lambda m: f"{flags[m.group(1)]} {m.group(2)}" if m.group(1) in flags else m.group(0), message)
    message = re.sub(r"(?<![\w.-])([a-z]+(?:_[a-z]+)+)(?![\w.(])",
                     lambda m: flags.get(m.group(1), m.group(1)), message)
    message = re.sub(r"\((--[\w/-]+), \1\)", r"(\1)", message)
    head = re.match(r"^(--[\w/-]+): ", message)
    if head:
        message = head.group(0) + message[head.end():].replace(f" ({head.group(1)})", "")
    return _one_prefix(message, flags)


def _one_prefix(message, flags=None):
    """``--x: --x: ...`` and ``--x: x: ...`` (``x`` the library's name of ``--x``) as ``--x: ...``."""
    match = re.match(r"^(--[\w-]+): ([\w-]+): ", message)
    if match and (match.group(2) == match.group(1) or match.group(2) == match.group(1)[2:] or
                  (flags is not None and flags.get(match.group(2)) == match.group(1))):
        message = f"{match.group(1)}: {message[match.end():]}"
    return message


def check_output_file(parser, flag, path):
    """Refuse (exit 2) an output file ``path`` that is an existing folder, whose folder does not exist, or in whose
    folder nothing can be written (checked by writing and removing a temporary file there, before any work)."""
    if path is None:
        return
    if os.path.isdir(path):
        parser.error(f"{flag}: expected a file name, got the folder {path!r}; name a file inside it")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        parser.error(f"{flag}: the folder of {path!r} does not exist; create it first" if not os.path.exists(folder)
                     else f"{flag}: the folder of {path!r} is a file, {folder!r}; name a file in a folder")
    problem = _unwritable(folder)
    if problem:
        parser.error(f"{flag}: cannot write {path!r} ({problem}); name a file in a folder you can write")


def check_output_folder(parser, flag, path, writable=True):
    """Refuse (exit 2) an output folder ``path`` that exists as a file and, with ``writable``, one that cannot be
    created (a file on its way, a place where no folder can be made) or in which nothing can be written; checked
    before any work by making and removing a temporary entry in it (or in the nearest folder above it that exists),
    so a refused ``path`` is left as it was and none is created. (``writable=False``: a command whose library checks
    that itself before its work, ta-export-print.)"""
    if path is None:
        return
    if os.path.exists(path) and not os.path.isdir(path):
        parser.error(f"{flag}: expected a folder, got the existing file {path!r}; name a new or existing folder")
    if not writable:
        return
    above = os.path.abspath(path)
    while not os.path.exists(above):
        above = os.path.dirname(above)
    if not os.path.isdir(above):
        parser.error(f"{flag}: cannot create the folder {path!r}: {above!r} is a file; name a folder elsewhere")
    problem = _unwritable(above)
    if problem and above == os.path.abspath(path):
        parser.error(f"{flag}: cannot write in the folder {path!r} ({problem}); name a folder you can write")
    if problem:
        parser.error(f"{flag}: cannot create the folder {path!r} ({problem} in {above!r}); name a folder you can "
                     f"write")


def _unwritable(folder):
    """None when an entry can be made (and is removed again) in ``folder``, else the reason (``strerror``)."""
    try:
        probe = tempfile.mkdtemp(prefix=".ta-write-probe-", dir=folder)
    except OSError as error:
        return error.strerror or str(error)
    os.rmdir(probe)
    return None
