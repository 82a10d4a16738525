"""What every long run needs from its machine and its run folder: an exclusive lock on the folder while the run writes
to it, shared by the readers of a finished run (:func:`lock_run_folder`), the tool that owns a run folder
(:func:`run_folder_owner`; :func:`claim_run_folder` refuses another tool's folder, locks it and marks it), a lock on
an output name while it is written (:func:`lock_output`), the memory it may use (:func:`memory_limits`: the
machine's, the address-space limit's, the cgroup's; :func:`available_memory_bytes`, :func:`check_memory`; the
tracer's own buffers, :func:`trace_buffer_bytes`), Ctrl-C held back while a step's state is written
(:func:`sigint_deferred`), the interruption that says how to resume (:class:`RunInterrupted`), and a checkpoint read
back with a message that names it when it is damaged (:func:`check_checkpoint`, :func:`load_checkpoint`)."""
import contextlib
import json
import os
import pickle
import threading
import zipfile

from ..interrupts import folder_listing, sigint_deferred  # noqa: F401  (sigint_deferred: part of this API)

__all__ = ["RunInterrupted", "lock_run_folder", "OWNER_FILE", "run_folder_owner", "check_run_folder_owner",
           "mark_run_folder", "claim_run_folder", "lock_output", "available_memory_bytes", "memory_limits",
           "gpu_memory_limits", "check_memory", "trace_buffer_bytes", "sigint_deferred", "check_checkpoint",
           "load_checkpoint"]

GiB = float(1 << 30)


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) during a run, after its checkpoint was written: the message says where and how to resume.

    Attributes:
        folder: the run folder. iteration: iterations done and saved in its checkpoint.
    """

    def __init__(self, message, folder, iteration):
        super().__init__(message)
        self.folder, self.iteration = folder, iteration


#: the run folders this process holds locked: (st_dev, st_ino) -> [(thread ident, exclusive), ...]
_HELD = {}
_HELD_GUARD = threading.Lock()


@contextlib.contextmanager
def lock_run_folder(folder, name="out", *, shared=False, reentrant=False,
                    advice="wait for it to end or choose another folder"):
    """Create ``folder`` if needed and hold a lock on it while the ``with`` block runs: a second run on the same
    folder (another process, or another thread) is refused at once instead of mixing its files with the first's. The
    lock is ``flock`` on the folder itself (no lock file is left behind) and goes with the process, so a killed run
    never leaves the folder locked. Without ``fcntl`` (Windows) the folder is not locked.

    Args:
        folder: the run folder. name: the argument to blame in the refusal. advice: what the refusal advises.
        shared: a reader's lock (an export of a finished run): readers share the folder, a run (exclusive) excludes
            them and is excluded by them.
        reentrant: when this thread already holds the folder's lock (exclusive, or shared for a shared request),
            go on under it instead of refusing: a run that exports its own package at its end.

    Yields:
        True when the block runs under a lock this thread already held (``reentrant``), else False.

    Raises:
        ValueError: naming ``name``, when another run (or, for a run, an export) holds the folder.
    """
    os.makedirs(folder, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield False
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        stat = os.fstat(fd)
        key, me = (stat.st_dev, stat.st_ino), threading.get_ident()
        with _HELD_GUARD:
            held = [exclusive for thread, exclusive in _HELD.get(key, ()) if thread == me]
        if reentrant and any(exclusive or shared for exclusive in held):
            yield True
            return
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = "a run that is writing it" if shared else "another run or export"
            raise ValueError(f"{name}: {folder!r} is in use by {holder} (it holds the folder's lock); "
                             f"{advice}") from None
        entry = (me, not shared)
        with _HELD_GUARD:
            _HELD.setdefault(key, []).append(entry)
        try:
            yield False
        finally:
            with _HELD_GUARD:
                _HELD[key].remove(entry)
                if not _HELD[key]:
                    del _HELD[key]
    finally:
        os.close(fd)  # releases the lock


#: the file in a run folder that names the ``ta-…`` tool whose folder it is (:func:`claim_run_folder` writes it)
OWNER_FILE = "tool.json"

#: how a folder written before :data:`OWNER_FILE` existed is known: (tool, entries only its folders hold), the first
#: match wins (a print run of an object holds object.npz too, so the print run comes before ta-voxelize); an export
#: package is known by its export.json alone (its files are listed exactly, it gets no tool.json)
_SIGNATURES = (
    ("ta-optimize-print", ("checkpoint.pt",)),
    ("ta-optimize-print", ("mixture.npz",)),
    ("ta-export-print", ("export.json",)),
    ("ta-select-inks", ("ranking.json",)),
    ("ta-select-inks", ("runs", "inks.json")),
    ("ta-fit-wood", ("board_estimate.json",)),
    ("ta-fit-wood", ("model.json", "params.json")),
    ("ta-render-wood-volume", ("veneer_fit.exr",)),
    ("ta-render-object", ("timings.json", "render.exr")),
    ("ta-voxelize", ("object.npz",)),
)


def run_folder_owner(folder):
    """The ``ta-…`` tool whose run folder ``folder`` is, and how that is known: ``(tool, how)``, or None for a
    folder that does not exist or that no tool has marked (a new or a user's own folder).

    A folder is marked by its :data:`OWNER_FILE` (``{"tool": "ta-fit-wood"}``, written by :func:`claim_run_folder`);
    one written before that file existed is known by the files only that tool writes (a print run's checkpoint.pt,
    a wood fit's board_estimate.json, an export package's export.json, ...).

    Example:
        >>> import tempfile
        >>> folder = tempfile.mkdtemp()
        >>> run_folder_owner(folder) is None
        True
        >>> mark_run_folder(folder, "ta-fit-wood")
        >>> run_folder_owner(folder)
        ('ta-fit-wood', 'its tool.json')
    """
    if not os.path.isdir(folder):
        return None
    marker = os.path.join(folder, OWNER_FILE)
    if os.path.exists(marker):
        try:
            with open(marker, encoding="utf-8") as f:
                tool = json.load(f).get("tool")
        except (OSError, ValueError, AttributeError):
            tool = None
        if not isinstance(tool, str) or not tool.startswith("ta-"):
            return ("another tool", f"its {OWNER_FILE} names none that can be read")
        return tool, f"its {OWNER_FILE}"
    names = set(os.listdir(folder))
    for tool, files in _SIGNATURES:
        if names.issuperset(files):
            return tool, f"it holds {' and '.join(files)}"
    return None


def check_run_folder_owner(folder, tool, name="out"):
    """Refuse a ``folder`` that another tool owns (:func:`run_folder_owner`) before ``tool`` writes to it.

    Raises:
        ValueError: ``"{name}: 'F' holds the output of ta-fit-wood (its tool.json); ta-optimize-print writes only into
            a new folder or one of its own: choose another folder (or remove that one)"``.
    """
    owner = run_folder_owner(folder)
    if owner is not None and owner[0] != tool:
        raise ValueError(f"{name}: {folder!r} holds the output of {owner[0]} ({owner[1]}); {tool} writes only into a "
                         f"new folder or one of its own: choose another folder (or remove that one)")


def mark_run_folder(folder, tool):
    """Write ``folder``'s :data:`OWNER_FILE` naming ``tool`` (atomically; left as it is when it already names it, so
    a later run of the same tool replaces no file by marking the folder)."""
    marker = os.path.join(folder, OWNER_FILE)
    if run_folder_owner(folder) == (tool, f"its {OWNER_FILE}"):
        return
    from .. import io as ta_io

    ta_io.write_json(marker, {"tool": tool})


@contextlib.contextmanager
def claim_run_folder(folder, tool, name="out", *, advice="wait for it to end or choose another folder"):
    """Own ``folder`` for the tool ``tool`` (``"ta-fit-wood"``) while the ``with`` block writes to it: a folder that
    another tool owns is refused (:func:`check_run_folder_owner`), the folder is created and locked
    (:func:`lock_run_folder`: a second process on it is refused at once), checked again under the lock and marked
    (:func:`mark_run_folder`). When the block ends (or raises) having changed nothing in the folder but the mark,
    the mark goes, and the folder too when the claim made it (a refused input leaves no folder behind).

    Raises:
        ValueError: naming ``name``, for another tool's folder or one that a run holds locked.
    """
    check_run_folder_owner(folder, tool, name)
    created = not os.path.isdir(folder)
    before = None
    try:
        with lock_run_folder(folder, name, advice=advice):
            check_run_folder_owner(folder, tool, name)  # again under the lock: another tool may have marked it
            if not os.path.exists(os.path.join(folder, OWNER_FILE)):
                before = (set(os.listdir(folder)), folder_listing(folder))
            mark_run_folder(folder, tool)
            yield
    finally:
        with contextlib.suppress(OSError):
            if before is not None:  # the mark is this claim's: it goes when nothing else was written
                names, files = set(os.listdir(folder)) - {OWNER_FILE}, folder_listing(folder)
                files.pop(OWNER_FILE, None)
                if (names, files) == before:
                    os.remove(os.path.join(folder, OWNER_FILE))
            if created and not os.listdir(folder):
                os.rmdir(folder)


@contextlib.contextmanager
def lock_output(path, name="out", *, advice="wait for it to end or choose another name"):
    """Hold an exclusive lock on the output name ``path`` (a file or folder written under a temporary name and renamed
    over ``path``, :func:`torch_appearance.io.atomic_output`) while the ``with`` block runs: a second writer of the
    same name is refused at once, so a check made inside the block (``path`` does not exist yet) still holds at the
    rename. The lock is ``flock`` on a file ``.NAME.lock`` beside ``path``, removed when the block ends (a writer that
    locked a removed one locks the new one instead); it goes with the process. The parent folder must exist. Without
    ``fcntl`` (Windows) nothing is locked.

    Raises:
        ValueError: naming ``name``, when another writer holds the name.
        OSError: the lock file cannot be created (a folder that is not writable).
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    folder, base = os.path.split(os.path.abspath(path))
    lock_path = os.path.join(folder, f".{base}.lock")
    while True:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise ValueError(f"{name}: {path!r} is being written by another process (it holds {lock_path!r}); "
                             f"{advice}") from None
        try:
            current = os.path.samestat(os.fstat(fd), os.stat(lock_path))
        except FileNotFoundError:
            current = False
        if current:
            break
        os.close(fd)  # the previous holder removed this file as it ended: lock the one at the name now
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock_path)  # still locked: a writer that opened it before finds it gone and retries
        os.close(fd)


#: a cgroup limit at or above this is "no limit" (cgroup v1 writes 2^63 rounded down to a page for "max")
_NO_LIMIT = 1 << 60


def memory_limits(proc="/proc", device=None):
    """What limits the memory a new allocation of this process can get, in bytes, by source (only the sources that
    apply; the smallest binds, :func:`available_memory_bytes`):

    - ``"MemAvailable"``: /proc/meminfo's estimate of what can be allocated without swapping (Linux), else
      ``"physical memory"``;
    - ``"address-space limit (ulimit -v)"``: ``RLIMIT_AS`` less the address space the process already maps
      (``VmSize``); ``"data limit (ulimit -d)"``: ``RLIMIT_DATA`` less ``VmData``;
    - ``"cgroup memory.max"`` (v2) and ``"cgroup memory.limit_in_bytes"`` (v1, the container's limit): the limit less
      the cgroup's usage without its reclaimable page cache (``inactive_file``), the smallest over the process's
      cgroup and those above it;
    - with a CUDA ``device``, ``"free memory of cuda:N"``: ``torch.cuda.mem_get_info(device)``'s free bytes (a run
      whose tensors live on the GPU is bound by them too; what the host limits say still applies to its host copies).

    Args:
        proc: where procfs is mounted (a test passes a folder with ``meminfo``, ``self/status``,
            ``self/cgroup`` and ``self/mountinfo``; the rlimits are then not read).
        device: the run's torch device (``"cuda"``, ``"cuda:1"``, a ``torch.device``); None or a CPU device adds
            nothing.

    Example:
        >>> limits = memory_limits()
        >>> all(isinstance(v, int) for v in limits.values())
        True
    """
    limits = {}
    meminfo = _read_fields(os.path.join(proc, "meminfo"))
    if "MemAvailable" in meminfo:
        limits["MemAvailable"] = meminfo["MemAvailable"]
    else:
        try:
            limits["physical memory"] = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (AttributeError, ValueError, OSError):  # pragma: no cover - no sysconf
            pass
    status = _read_fields(os.path.join(proc, "self", "status"))
    if proc == "/proc":
        try:
            import resource
        except ImportError:  # pragma: no cover - Windows
            resource = None
        if resource is not None:
            for rlimit, used, source in ((resource.RLIMIT_AS, "VmSize", "address-space limit (ulimit -v)"),
                                         (getattr(resource, "RLIMIT_DATA", None), "VmData", "data limit (ulimit -d)")):
                if rlimit is None:
                    continue
                soft = resource.getrlimit(rlimit)[0]
                if soft != resource.RLIM_INFINITY and soft >= 0:
                    limits[source] = max(0, soft - status.get(used, 0))
    for source, left in _cgroup_room(proc).items():
        limits[source] = left
    limits.update(gpu_memory_limits(device))
    return limits


def gpu_memory_limits(device):
    """``{"free memory of cuda:N": bytes}`` for a CUDA ``device`` (``torch.cuda.mem_get_info``: free memory on the
    device as the driver reports it, other processes' allocations included); {} for None or another device."""
    if device is None:
        return {}
    import torch

    device = torch.device(device)
    if device.type != "cuda" or not torch.cuda.is_available():  # no CUDA: the run itself says so
        return {}
    index = device.index if device.index is not None else torch.cuda.current_device()
    free, _ = torch.cuda.mem_get_info(index)
    return {f"free memory of cuda:{index}": int(free)}


def available_memory_bytes(proc="/proc", device=None):
    """Memory a new allocation of this process can get: the smallest of :func:`memory_limits` (``MemAvailable``,
    ``RLIMIT_AS`` and ``RLIMIT_DATA`` less what is mapped, the cgroup v2/v1 limit less its usage, a CUDA ``device``'s
    free memory); None when none is known."""
    limits = memory_limits(proc, device)
    return min(limits.values()) if limits else None


def _read_fields(path):
    """``Name: value kB`` lines (/proc/meminfo, /proc/self/status) as bytes by name; {} when unreadable."""
    fields = {}
    try:
        with open(path) as f:
            for line in f:
                name, _, value = line.partition(":")
                parts = value.split()
                if parts and parts[0].isdigit():
                    fields[name.strip()] = int(parts[0]) * (1024 if parts[1:2] == ["kB"] else 1)
    except OSError:
        pass
    return fields


def _read_int(path):
    try:
        with open(path) as f:
            text = f.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None  # "max" (v2): no limit


def _cgroup_room(proc):
    """{source: bytes left} of the memory cgroups (v2 and v1) that hold this process, from /proc/self/cgroup and the
    mounts of /proc/self/mountinfo."""
    try:
        with open(os.path.join(proc, "self", "cgroup")) as f:
            lines = f.read().splitlines()
        with open(os.path.join(proc, "self", "mountinfo")) as f:
            mounts = f.read().splitlines()
    except OSError:
        return {}
    paths = {}  # "v2" / "v1" -> the process's cgroup path
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) == 3 and parts[0] == "0" and parts[1] == "":
            paths["v2"] = parts[2]
        elif len(parts) == 3 and "memory" in parts[1].split(","):
            paths["v1"] = parts[2]
    room = {}
    for line in mounts:
        fields = line.split()
        if " - " not in line or len(fields) < 5:
            continue
        tail = line.split(" - ", 1)[1].split()
        fstype, options = tail[0], (tail[2] if len(tail) > 2 else "")
        root, mountpoint = fields[3], fields[4]
        if fstype == "cgroup2" and "v2" in paths:
            files = ("cgroup memory.max", "memory.max", "memory.current")
            path = paths["v2"]
        elif fstype == "cgroup" and "memory" in options.split(",") and "v1" in paths:
            files = ("cgroup memory.limit_in_bytes", "memory.limit_in_bytes", "memory.usage_in_bytes")
            path = paths["v1"]
        else:
            continue
        source, limit_name, usage_name = files
        relative = path[len(root):] if path.startswith(root) and root != "/" else path
        folder = os.path.normpath(mountpoint + "/" + relative.lstrip("/"))
        if not folder.startswith(os.path.normpath(mountpoint)) or not os.path.isdir(folder):
            folder = mountpoint  # a namespaced view: the process's cgroup is the mount's root
        best = None
        while True:  # the process's cgroup and each above it, up to the mount point
            limit = _read_int(os.path.join(folder, limit_name))
            if limit is not None and limit < _NO_LIMIT:
                usage = _read_int(os.path.join(folder, usage_name)) or 0
                cache = _read_fields_plain(os.path.join(folder, "memory.stat")).get("inactive_file", 0)
                left = max(0, limit - max(0, usage - cache))
                best = left if best is None else min(best, left)
            if os.path.normpath(folder) == os.path.normpath(mountpoint):
                break
            folder = os.path.dirname(folder)
        if best is not None:
            room[source] = min(best, room.get(source, best))
    return room


def _read_fields_plain(path):
    """``name value`` lines (a cgroup's memory.stat) as a dict of ints; {} when unreadable."""
    fields = {}
    try:
        with open(path) as f:
            for line in f:
                parts = line.split()
                if len(parts) == 2 and parts[1].isdigit():
                    fields[parts[0]] = int(parts[1])
    except OSError:
        pass
    return fields


def check_memory(name, need_bytes, what, fix, available=None, device=None):
    """Refuse work that would not fit in memory, before anything is written.

    Args:
        name: the argument to blame. need_bytes: the estimate. what: what needs it ("a 1644×1644×12 slab").
        fix: what to change. available: bytes available (default: the smallest of :func:`memory_limits`, so an
            address-space limit (``ulimit -v``) or a container's cgroup limit refuses as the machine's memory does).
        device: the run's torch device; a CUDA one's free memory is one of the limits (named when it binds).

    Raises:
        ValueError: ``"{name}: {what} needs about X GiB of memory, this machine has Y GiB available; {fix}"``, or
            ``"... this process may use Y GiB (its address-space limit (ulimit -v)); {fix}"`` when a limit of the
            process binds before the machine's memory, ``"... cuda:0 has Y GiB free; {fix}"`` when the GPU's free
            memory binds.
    """
    source = None
    if available is None:
        limits = memory_limits(device=device)
        if limits:
            source, available = min(limits.items(), key=lambda item: item[1])
    if available is not None and need_bytes > available:
        digits = 1 if f"{need_bytes / GiB:.1f}" != f"{available / GiB:.1f}" else 3  # "needs 0.3, may use 0.3"
        if source in (None, "MemAvailable", "physical memory"):
            have = f"this machine has {available / GiB:.{digits}f} GiB available"
        elif source.startswith("free memory of "):  # a GPU's
            have = f"{source[len('free memory of '):]} has {available / GiB:.{digits}f} GiB free"
        else:
            have = f"this process may use {available / GiB:.{digits}f} GiB (its {source})"
        raise ValueError(f"{name}: {what} needs about {need_bytes / GiB:.{digits}f} GiB of memory, {have}; {fix}")


#: sensor elements a tracer thread walks at once (``kSimdBatch`` of csrc/volpath/simd_glue.h)
TRACE_BATCH = 256


def trace_buffer_bytes(spp, elements, threads=None):
    """Memory in bytes of the tracer's per-thread buffers for a render at ``spp`` samples per element: each thread
    holds every path's value of a batch of up to :data:`TRACE_BATCH` sensor elements (3 doubles per path) before it
    sums them in sample order (``simd_forward_batches``), so a huge ``spp`` fails in the allocator (``std::bad_alloc``)
    however small the image. ``threads``: default ``torch.get_num_threads()``.

    Example:
        >>> trace_buffer_bytes(32, 10_000, threads=2) == 2 * 256 * 32 * 24
        True
    """
    if threads is None:
        import torch
        threads = torch.get_num_threads()
    return int(threads) * min(TRACE_BATCH, max(1, int(elements))) * int(spp) * 3 * 8


#: the entries of a print run's checkpoint (pipelines/print/loop.py, ``_Run.checkpoint``)
CHECKPOINT_KEYS = ("model", "optimizer", "rows", "iteration", "wall_s", "baseline", "grid_dhw", "inks")


def check_checkpoint(path, name="resume"):
    """Refuse a checkpoint file that cannot be a whole one, cheaply (without reading its tensors): missing, empty, or
    without the zip directory that ``torch.save`` writes last (a truncated file, a copy cut short).

    Raises:
        ValueError: ``"{name}: the checkpoint '{path}' cannot be read (...): it is truncated or damaged; ..."``.
    """
    if not os.path.isfile(path):
        raise ValueError(f"{name}: no checkpoint {path!r} (no such file)")
    try:
        with zipfile.ZipFile(path) as archive:
            if not any(n.endswith("/data.pkl") or n == "data.pkl" for n in archive.namelist()):
                raise zipfile.BadZipFile("no data.pkl in it")
    except (OSError, zipfile.BadZipFile, EOFError) as error:
        raise ValueError(_damaged(name, path, error)) from None


def load_checkpoint(path, name="resume", keys=CHECKPOINT_KEYS):
    """``torch.load`` of a run's checkpoint (a dict written by the run itself, so not ``weights_only``) onto the CPU
    (one saved with CUDA tensors loads on a machine without a GPU; the run moves them to its device), with a
    damaged file (truncated, cut short, overwritten, missing one of ``keys``) refused by a message that names it,
    instead of the reader's own error.

    Raises:
        ValueError: ``"{name}: the checkpoint '{path}' cannot be read (...): it is truncated or damaged; ..."``.
    """
    import torch

    check_checkpoint(path, name)
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)  # a GPU run's tensors too: any machine
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile, AttributeError,
            ImportError) as error:
        raise ValueError(_damaged(name, path, error)) from None
    missing = [key for key in keys if not isinstance(state, dict) or key not in state]
    if missing:
        raise ValueError(_damaged(name, path, f"no {', '.join(missing)} in it"))
    return state


def _damaged(name, path, error):
    reason = str(error).split(". ")[0].strip() or type(error).__name__
    if isinstance(error, zipfile.BadZipFile) and "not a zip file" in reason:
        reason = "it does not end in the zip directory torch.save writes"
    return (f"{name}: the checkpoint {path!r} cannot be read ({reason}): it is truncated or damaged; start the run "
            f"again in a new folder (or remove the folder)")
