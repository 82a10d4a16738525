"""Printer packages of a finished print run: GrabCAD Voxel Print (``.gcvf``), 3MF and the PNG slice stack.

:func:`export_run` reads a run folder that :func:`~.loop.optimize_print` wrote and writes, for one printer profile
(:func:`~torch_appearance.fabrication.printer.load_printer`), a package folder::

    OUT/print.gcvf      GrabCAD Voxel Print: layer PNGs + ConfigFile.xml (:mod:`~torch_appearance.fabrication.gcvf`)
    OUT/print.3mf       the object at its printed size coloured by the rendered print (any 3MF viewer shows it)
    OUT/print-volume.3mf  the same with the per-voxel material volume (3MF Volumetric extension, as far as lib3mf
                        writes it: :mod:`~torch_appearance.fabrication.threemf`); lib3mf marks such a file as
                        requiring the Volumetric extension, so viewers without it refuse it, hence the two files
    OUT/slices/         one palette PNG per layer + palette.json (:func:`~torch_appearance.fabrication.export_slices`)
    OUT/export.json     what was written: printer, formats, layers, printed size, source of the volume, seconds

The volume is streamed layer by layer, so memory does not grow with the number of layers:

* when the printer's voxels are the run's (:meth:`PrinterProfile.matches`, within 1 % per axis) and the run's
  halftoning is kept, the layers are read one at a time from the run's ``quantized.npz``: the package holds exactly
  the run's quantised volume;
* otherwise (another layer thickness or DPI, or another ``halftone``) the run's mixture (``mixture.npz``) is
  quantised again at the printer's resolution with the run's quantisation seed
  (:class:`~torch_appearance.fabrication.quantize.iter_quantized`), an object's outside marked void block by block
  (:func:`.object_target.outside_micro_centres`).

Everything is written into a temporary folder beside ``OUT`` and renamed at the end: a failed or interrupted export
leaves no partial package. The export holds two locks for its whole length
(:mod:`torch_appearance.pipelines.runs`): the run folder's, shared with other exports (a run that is optimising or
writing its results holds it alone, so an export never reads a volume that is being replaced), and the name ``OUT``'s
(:func:`~torch_appearance.pipelines.runs.lock_output`), under which an existing ``OUT`` is refused unless ``force``: of
two exports to one ``OUT`` the second is refused, whichever comes first; another tool's folder is refused even with
``force`` (:func:`~torch_appearance.pipelines.runs.check_run_folder_owner`). ``export.json`` records the run's
iteration that was packaged.

What differs between a slab run and an object run (its rendered texels, the mesh of ``print.3mf``, the void outside
a requantised object) is a method of its reader, :class:`SlabRun` or :class:`ObjectRun`; :func:`open_run` picks the
reader from the run's ``config.json`` once.
"""
import csv
import os
import time

import numpy as np

from ... import io as ta_io
from ...color import linear_to_srgb8
from ...fabrication.export import VOID, IndexVolumeLayers, export_slices, npy_header
from ...fabrication.inks import InkSet, ink_from_dict
from ...fabrication.printer import load_printer
from ...fabrication.quantize import HALFTONES, iter_quantized, micro_grid_pitch
from ..runs import check_memory, check_run_folder_owner, lock_output, lock_run_folder
from .config import iteration_seed

__all__ = ["export_run", "open_run", "run_layers", "RunFolder", "SlabRun", "ObjectRun", "FORMATS"]

#: The package formats, in the order they are written.
FORMATS = ("gcvf", "3mf", "slices")
#: the tool whose folders the packages are (known by their export.json, :func:`~.runs.run_folder_owner`)
TOOL = "ta-export-print"


def _check_run_folder(folder):
    if not isinstance(folder, (str, os.PathLike)):
        raise TypeError(f"run: expected a run folder path, got {type(folder).__name__}")
    folder = os.fspath(folder)
    if not os.path.isdir(folder):
        raise ValueError(f"run: {folder!r} is not a folder")
    return folder


def open_run(folder):
    """The reader of the print run in ``folder`` for its target type (:class:`SlabRun` or :class:`ObjectRun`), its
    files checked once. Read a run under its lock (:func:`export_run` does): a run that is writing its results may
    replace them meanwhile.

    Raises:
        TypeError, ValueError: not a folder, not a print run, a run from an incompatible version, an unfinished run.
    """
    folder = _check_run_folder(folder)
    path = os.path.join(folder, "config.json")
    if not os.path.isfile(path):
        raise ValueError(f"run: {folder!r} is not a print run (no config.json)")
    config = ta_io.read_json(path, name="run config.json")
    needed = ("kind", "inks", "voxel_size_mm", "printer_dpi", "seed")
    missing = [k for k in needed if k not in config]
    if missing or config.get("kind") not in RUN_TYPES:
        raise ValueError(f"run: {folder!r} was written by an incompatible version of torch_appearance "
                         f"(config.json lacks {missing or ['a known kind']}); optimise it again")
    return RUN_TYPES[config["kind"]](folder, config)


class RunFolder:
    """What an export needs from a run folder, checked once: its config, inks, grid, quantised volume. The target
    type's part (:meth:`final_texels`, :meth:`mesh`, :meth:`outside`) is in :class:`SlabRun` and :class:`ObjectRun`;
    open a run with :func:`open_run`."""

    def __init__(self, folder, config):
        self.folder, self.config = folder, config
        path = os.path.join(self.folder, "config.json")
        self.inks = InkSet([ink_from_dict(e, where=f"{path}: inks[{i}]") if isinstance(e, dict) else e
                            for i, e in enumerate(self.config["inks"])])
        self.quantized = os.path.join(self.folder, "quantized.npz")
        if not os.path.isfile(self.quantized):
            raise ValueError(f"run: {self.folder!r} has no quantized.npz: the run has not finished (resume it with "
                             f"ta-optimize-print --resume --out {self.folder})")
        self.layers = IndexVolumeLayers(self.quantized)
        if [i.name for i in self.layers.inks] != [i.name for i in self.inks]:
            raise ValueError(f"run: quantized.npz holds inks {list(self.layers.inks.names)}, config.json "
                             f"{list(self.inks.names)}")
        self.voxel_size = float(self.config["voxel_size_mm"])
        self.halftone = self.config.get("halftone", "random")

    def iteration(self, finishing=False):
        """The iteration of the run whose results (``quantized.npz``, ``mixture.npz``) the folder holds: the last of
        ``log.csv``, which ``summary.json`` must confirm unless ``finishing`` (the run itself exporting its package,
        before it writes its summary).

        Raises:
            ValueError: a run that has not finished: no log or summary, or a log beyond the summary (a run that
                ``--resume`` extended and that was interrupted before it wrote its results).
        """
        resume = f"ta-optimize-print --resume --out {self.folder}"
        try:
            with open(os.path.join(self.folder, "log.csv"), newline="") as handle:
                rows = list(csv.DictReader(handle))
            logged = int(float(rows[-1]["iteration"]))
        except (OSError, IndexError, KeyError, TypeError, ValueError):
            raise ValueError(f"run: {self.folder!r} has no readable log.csv: the run has not finished (resume it "
                             f"with {resume})") from None
        if finishing:
            return logged
        path = os.path.join(self.folder, "summary.json")
        if not os.path.isfile(path):
            raise ValueError(f"run: {self.folder!r} has no summary.json: the run has not finished (resume it with "
                             f"{resume})")
        summarised = ta_io.read_json(path, name="run summary.json").get("iterations")
        if summarised != logged:
            raise ValueError(f"run: {self.folder!r} was extended to iteration {logged} but its results are of "
                             f"iteration {summarised}: the run has not finished (resume it with {resume})")
        return logged

    def mixture(self):
        path = os.path.join(self.folder, "mixture.npz")
        if not os.path.isfile(path):
            raise ValueError(f"run: {self.folder!r} has no mixture.npz to quantise at another resolution")
        with np.load(path, allow_pickle=False) as data:
            return data["weights"]

    def mixture_shape(self):
        """(N, D, H, W) of ``mixture.npz``, from the array's header (the weights are not decompressed)."""
        import zipfile

        path = os.path.join(self.folder, "mixture.npz")
        try:
            with zipfile.ZipFile(path) as archive, archive.open("weights.npy") as handle:
                return tuple(int(v) for v in npy_header(handle, "mixture.npz")[0])
        except (OSError, KeyError, ValueError, zipfile.BadZipFile) as error:
            raise ValueError(f"run: {self.folder!r}: mixture.npz is missing or unreadable ({error})") from None

    def final_texels(self):
        """The rendered quantised print, linear RGB (its shape is the target type's)."""
        raise NotImplementedError

    def mesh(self, macro_shape):
        """The surface of ``print.3mf``: (vertices (V, 3) mm, faces (F, 3) int64, colours: ``vertex_rgb`` or
        ``face_rgb`` uint8 sRGB) for :func:`~torch_appearance.fabrication.threemf.write_3mf`. ``macro_shape``: (N, D,
        H, W) of the run's mixture."""
        raise NotImplementedError

    def outside(self, micro_shape):
        """None, or ``outside(z0, z1)`` -> bool (z1 - z0, Hy, Wx): the printer voxels of layers z0..z1 of a
        ``micro_shape`` (Dz, Hy, Wx) volume that lie outside the object, void in a requantised volume."""
        raise NotImplementedError


class SlabRun(RunFolder):
    """A slab run: the box of the run's grid, its top (and bottom) face rendered."""

    def final_texels(self):
        """(F, H, W, 3) faces of the slab (top, and bottom when the run rendered it), linear RGB."""
        stems = ["final"] + (["final_bottom"] if os.path.isfile(os.path.join(self.folder, "final_bottom.exr")) else [])
        return np.stack([ta_io.read_exr(os.path.join(self.folder, f"{s}.exr")) for s in stems])

    def mesh(self, macro_shape):
        return _slab_mesh(self, macro_shape)

    def outside(self, micro_shape):
        return None  # every voxel of the box is printed


class ObjectRun(RunFolder):
    """An object run: a mesh's SDF in the run's grid (``object.npz``), its surface texels rendered."""

    def object_sdf(self):
        with np.load(os.path.join(self.folder, "object.npz"), allow_pickle=False) as data:
            return data["sdf"], data["texel_points"], tuple(data["origin"].tolist())

    def final_texels(self):
        """(N, 3) surface texels, linear RGB."""
        return np.load(os.path.join(self.folder, "final.npy"))

    def mesh(self, macro_shape):
        return _object_mesh(self)

    def outside(self, micro_shape):
        from .object_target import outside_micro_centres
        return outside_micro_centres(self.object_sdf()[0], micro_shape)


#: the reader of each kind of run (``config.json``'s ``kind``)
RUN_TYPES = {"slab": SlabRun, "object": ObjectRun}


class _Requantized:
    """Layer source: the run's mixture quantised again at ``dpi`` (an object's outside void), one block at a time."""

    def __init__(self, run, dpi, halftone):
        if run.config.get("fixed"):
            raise ValueError(f"printer: the run holds fixed ink fractions ({run.config['fixed']}), which are exact "
                             f"only at the run's own resolution {tuple(run.layers.dpi)}; export it for a printer with "
                             f"that resolution, or optimise again with --printer")
        self.weights = run.mixture()
        self.blocks = iter_quantized(self.weights, run.voxel_size, dpi,
                                     iteration_seed(run.config["seed"], -2), halftone)
        self.shape = self.blocks.shape
        self.outside = run.outside(self.shape)

    def __len__(self):
        return self.shape[0]

    def __iter__(self):
        for z0, block in self.blocks:
            if self.outside is not None:
                block[self.outside(z0, z0 + len(block))] = VOID
            yield from block


def run_layers(run, printer, halftone=None):
    """The layer source of ``run`` (a :class:`RunFolder`, :func:`open_run`) for ``printer`` and how it was made (see
    the module).

    Returns:
        (layers, source, dpi): an object with ``shape`` that yields the (Hy, Wx) uint8 layers; ``"run"`` or
        ``"requantized"``; the (x, y, z) DPI of the volume.
    """
    halftone = run.halftone if halftone is None else halftone
    if not _requantizes(run, printer, halftone):
        return run.layers, "run", tuple(run.layers.dpi)
    return _Requantized(run, printer.dpi, halftone), "requantized", printer.dpi


def _requantizes(run, printer, halftone):
    """Whether ``run`` is quantised again for ``printer`` with ``halftone`` (None: the run's), or its own volume is
    packaged."""
    halftone = run.halftone if halftone is None else halftone
    if halftone not in HALFTONES:
        raise ValueError(f"halftone: expected one of {HALFTONES}, got {halftone!r}")
    return not (printer.matches(run.layers.dpi) and halftone == run.halftone)


#: peak memory of an export over the imported package: Spot at 40 mm (5 × 475 × 467 × 262 mixture) took 549 MB
#: from the run's volume and 2.0 GB quantised again (1.16 GB of it the float32 mixture, loaded whole), at 20 mm 169
#: and 367 MB (docs/bench_log.md, "Printer packages"): 0.25 GiB + 12 bytes per voxel of the run's grid, + 4 bytes
#: per ink and voxel when quantised again, covers them
EXPORT_FIXED_BYTES = 1 << 28
EXPORT_BYTES_PER_VOXEL = 12


def export_memory_bytes(mixture_shape, requantized):
    """Expected peak memory in bytes of exporting a run with an (N, D, H, W) mixture.

    Example:
        >>> round(export_memory_bytes((5, 262, 467, 475), True) / 2**30, 1)   # Spot at 40 mm for a j750-hq
        2.0
    """
    n, voxels = int(mixture_shape[0]), int(np.prod(mixture_shape[1:], dtype=np.float64))
    return EXPORT_FIXED_BYTES + voxels * (EXPORT_BYTES_PER_VOXEL + (4 * n if requantized else 0))


def _object_mesh(run, block=24):
    """The printed surface of an object run: the zero set of its SDF (the printer prints the voxels whose centre is
    inside it) by marching cubes, in the print box's mm (origin at the grid corner), each vertex coloured by its
    nearest texel of the rendered print. The cubes go ``block`` corner layers at a time (the corner coordinates of
    the whole grid would take 24 bytes per corner: 1 GB at 40 mm); the vertices that neighbouring blocks share on
    their common corner layer are computed from the same values and merged."""
    import igl
    from scipy.spatial import cKDTree

    sdf, texel_points, origin = run.object_sdf()
    d, h, w = sdf.shape
    s = run.voxel_size
    j, i = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    plane = np.stack([i.reshape(-1), j.reshape(-1)], axis=1).astype(np.float64) * s      # (H·W, 2) x, y
    vertices, faces, offset = [], [], 0
    for k0 in range(0, d - 1, block):
        k1 = min(d, k0 + block + 1)                                # corner layers k0 .. k1-1 (shared with the next)
        grid = np.concatenate([np.c_[plane, np.full(len(plane), k * s)] for k in range(k0, k1)])
        v, f, _ = igl.marching_cubes(np.ascontiguousarray(sdf[k0:k1].reshape(-1), np.float64), grid, w, h, k1 - k0,
                                     0.0)
        if len(f):
            vertices.append(v)
            faces.append(f + offset)
            offset += len(v)
    vertices, faces = np.concatenate(vertices), np.concatenate(faces)
    vertices, inverse = np.unique(vertices, axis=0, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    texels = texel_points - np.asarray(origin)[None, :]
    _, nearest = cKDTree(texels).query(vertices)
    return vertices, faces, {"vertex_rgb": linear_to_srgb8(run.final_texels()[nearest])}


def _slab_mesh(run, shape):
    """A closed box of the slab's size; its top (and bottom) face a grid of one quad per texel coloured by the
    rendered print's texel, the side walls strips that share the faces' edge vertices (watertight)."""
    _, _, h, w = shape
    depth = shape[1] * run.voxel_size
    s = run.voxel_size
    faces_rgb = linear_to_srgb8(run.final_texels())                       # (F, H, W, 3)
    xs, ys = np.arange(w + 1) * s, np.arange(h + 1) * s
    gx, gy = np.meshgrid(xs, ys)                                 # (H+1, W+1)
    top = np.stack([gx, gy, np.full_like(gx, depth)], -1).reshape(-1, 3)
    bottom = np.stack([gx, gy, np.zeros_like(gx)], -1).reshape(-1, 3)
    vertices = np.concatenate([top, bottom])
    n = (h + 1) * (w + 1)
    jj, ii = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    a = (jj * (w + 1) + ii).reshape(-1)
    b, c, e = a + 1, a + w + 1, a + w + 2
    top_faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, e], 1)])[:, ::-1]   # normals up (+z)
    bottom_faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, e], 1)]) + n       # normals down
    top_rgb = np.concatenate([faces_rgb[0].reshape(-1, 3)] * 2)
    bottom_rgb = np.concatenate([faces_rgb[-1].reshape(-1, 3)] * 2) if len(faces_rgb) == 2 else \
        np.repeat(np.round(faces_rgb[0].reshape(-1, 3).mean(0)).astype(np.uint8)[None], len(bottom_faces), 0)
    ring = ([(0, x) for x in range(w)] + [(y, w) for y in range(h)] + [(h, x) for x in range(w, 0, -1)]
            + [(y, 0) for y in range(h, 0, -1)])                 # the boundary, counter-clockwise seen from +z
    ring_idx = np.array([y * (w + 1) + x for y, x in ring])
    nxt = np.roll(ring_idx, -1)
    sides = np.concatenate([np.stack([ring_idx, ring_idx + n, nxt], 1), np.stack([nxt, ring_idx + n, nxt + n], 1)])
    ys_, xs_ = np.array([min(y, h - 1) for y, _ in ring]), np.array([min(x, w - 1) for _, x in ring])
    side_rgb = np.concatenate([faces_rgb[0][ys_, xs_]] * 2)
    faces = np.concatenate([top_faces, bottom_faces, sides]).astype(np.int64)
    return vertices, faces, {"face_rgb": np.concatenate([top_rgb, bottom_rgb, side_rgb])}


def export_run(run, out=None, printer="j750", formats=("gcvf", "3mf"), *, halftone=None, force=False, progress=True,
               log=print):
    """Write the printer package of a finished print run (see the module docstring for the layout and the locks).

    Args:
        run: the run folder (``ta-optimize-print --out``), with ``quantized.npz``, ``log.csv`` and ``summary.json``
            (the run's own export at its end needs no summary).
        out: the package folder; default ``RUN/package-PRINTER``. An existing one is refused unless ``force``.
        printer: a profile name, a profile JSON path or a :class:`~torch_appearance.fabrication.printer.PrinterProfile`.
        formats: any of :data:`FORMATS`.
        halftone: ``None`` (the run's), or one of :data:`~torch_appearance.fabrication.quantize.HALFTONES`.
        force: replace an existing ``out``.
        progress: progress bars over the layers (:func:`~torch_appearance.progress.progress_bar`). log: one-line
            messages.

    Returns:
        The dict written to ``export.json``; its ``iteration`` is the run's iteration that was packaged.

    Raises:
        TypeError, ValueError: an unknown printer, an ink the printer does not hold, an unknown format, an existing
            ``out``, an ``out`` that another export is writing or that cannot be written, a run folder without a
            quantised volume, unfinished, from an incompatible version or locked by a run that is writing it; before
            anything is written (an ``out`` that fails while it is written: after, and then nothing is left).
    """
    t0 = time.perf_counter()
    folder = _check_run_folder(run)
    with lock_run_folder(folder, "run", shared=True, reentrant=True,
                         advice="wait for it to end, then export it") as finishing:
        run = open_run(folder)
        iteration = run.iteration(finishing)  # inside the run's lock, the run is exporting its own package
        printer = load_printer(printer)
        if isinstance(formats, str):
            formats = [f.strip() for f in formats.split(",") if f.strip()]
        formats = list(dict.fromkeys(formats))
        unknown = [f for f in formats if f not in FORMATS]
        if unknown or not formats:
            raise ValueError(f"formats: expected some of {FORMATS}, got {formats}")
        printer.material_indices(run.inks.names)  # an ink the printer lacks: refused before anything is written
        out = os.path.join(run.folder, f"package-{printer.name}") if out is None else os.fspath(out)
        check_run_folder_owner(out, TOOL)  # --force replaces a package, never another tool's folder
        if os.path.exists(out) and not force:  # early, before the volume is prepared; again under out's lock
            raise _exists(out)
        shape = run.mixture_shape()
        check_memory("run", export_memory_bytes(shape, _requantizes(run, printer, halftone)),
                     f"exporting a run of {' × '.join(map(str, shape[1:]))} voxels and {shape[0]} inks for "
                     f"{printer.name}", "export on a machine with more memory, or for a printer whose resolution "
                     "the run was quantised at (no new quantisation)")
        layers, source, dpi = run_layers(run, printer, halftone)
        dz, hy, wx = layers.shape
        macro = run.mixture_shape() if "3mf" in formats else None          # (N, D, H, W)
        pitch = micro_grid_pitch(macro[1:], run.voxel_size, dpi) if macro else None
        record = {"run": os.path.abspath(run.folder), "iteration": iteration, "printer": printer.to_dict(),
                  "formats": formats, "volume": source, "halftone": run.halftone if halftone is None else halftone,
                  "shape_zyx": [dz, hy, wx], "dpi": list(dpi),
                  "printed_size_mm": [wx * 25.4 / printer.dpi[0], hy * 25.4 / printer.dpi[1],
                                      dz * printer.layer_thickness_nm * 1e-6], "files": {}, "seconds": {}}
        tmp = None
        try:
            os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
            with lock_output(out, "out", advice="wait for it to end or write elsewhere"):
                check_run_folder_owner(out, TOOL)
                if os.path.exists(out) and not force:  # another export may have written it meanwhile
                    raise _exists(out)
                with ta_io.atomic_output(out, folder=True) as tmp:   # a failed export leaves no partial package
                    _write_package(tmp, run, printer, formats, layers, dpi, macro, pitch, record, progress)
                    record["seconds"]["total"] = round(time.perf_counter() - t0, 3)
                    ta_io.write_json(os.path.join(tmp, "export.json"), record)
        except OSError as error:
            raise _write_error(error, out, tmp) from None
    log(f"export: {', '.join(formats)} for {printer.name} ({dz} layers of {wx} x {hy}, {source} volume of iteration "
        f"{iteration}) in {record['seconds']['total']:.1f} s -> {out}")
    return record


def _write_package(tmp, run, printer, formats, layers, dpi, macro, pitch, record, progress):
    """The package's files in the folder ``tmp``, their entries in ``record["files"]`` and ``record["seconds"]``."""
    dz, hy, wx = layers.shape
    for fmt in formats:
        t = time.perf_counter()
        bar = _bar(progress, dz, f"{fmt} ({printer.name})")
        tick = None if bar is None else (lambda k: bar.update(1))
        if fmt == "gcvf":
            from ...fabrication.gcvf import write_gcvf
            info = write_gcvf(os.path.join(tmp, "print.gcvf"), layers, printer, run.inks.names, progress=tick)
            record["files"]["print.gcvf"] = info
        elif fmt == "3mf":
            from ...fabrication.threemf import write_3mf
            vertices, faces, colours = run.mesh(macro)
            materials = [printer.materials[m] for m in printer.material_indices(run.inks.names)]
            # two files: lib3mf marks a file holding a volume as requiring the Volumetric extension, and a
            # viewer without it must refuse the whole file; the coloured mesh alone opens anywhere
            write_3mf(os.path.join(tmp, "print.3mf"), vertices, faces, **colours)
            write_3mf(os.path.join(tmp, "print-volume.3mf"), vertices, faces, layers=iter(layers),
                      grid_shape=(dz, hy, wx), pitch_mm=pitch, materials=materials, progress=tick, **colours)
            for name in ("print.3mf", "print-volume.3mf"):
                record["files"][name] = {"triangles": int(len(faces)), "vertices": int(len(vertices)),
                                         "bytes": os.path.getsize(os.path.join(tmp, name))}
            record["files"]["print-volume.3mf"]["materials"] = [m[0] for m in materials]
        else:
            export_slices(layers, run.inks, os.path.join(tmp, "slices"), dpi=dpi, progress=tick)
            record["files"]["slices"] = {"layers": dz}
        if bar is not None:
            bar.close()
        record["seconds"][fmt] = round(time.perf_counter() - t, 3)


def _exists(out):
    return ValueError(f"out: {out!r} exists; pass force=True (--force) to replace it")


def _write_error(error, out, tmp):
    """An ``OSError`` of writing ``out`` as a ``ValueError`` that names ``out`` and not what the export makes beside
    it (its temporary folder ``.OUT.*.tmp``, its lock file ``.OUT.lock``) or the folders it creates above it; any other
    ``OSError`` (reading the run, say) is returned as it is."""
    full = os.path.abspath(out)
    where, base = os.path.split(full)

    def ours(name):
        name = os.path.abspath(name)
        return (name == full or full.startswith(name + os.sep)                    # out, or a folder above it
                or (os.path.dirname(name) == where and os.path.basename(name).startswith(f".{base}."))
                or (tmp is not None and name.startswith(os.path.abspath(tmp) + os.sep)))

    names = [f for f in (error.filename, error.filename2) if isinstance(f, (str, bytes, os.PathLike))]
    if names and not all(ours(os.fsdecode(n)) for n in names):
        return error
    return ValueError(f"out: cannot write the package {out!r}: {error.strerror or error}")


def _bar(progress, total, desc):
    if not progress:
        return None
    from ...progress import progress_bar

    return progress_bar(total=total, desc=desc, unit="layer", leave=False)
