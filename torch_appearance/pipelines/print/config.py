"""The settings of one print optimisation (:class:`PrintConfig`), the ink set they name, and the run's seeds."""
import dataclasses
import math
import os
from dataclasses import dataclass, fields
from typing import Optional, Sequence, Tuple, Union

from ...checks import check_device
from ...fabrication.inks import DEFAULT_INKS, Ink, InkSet, ink_from_dict
from ...fabrication.printer import load_printer
from ...fabrication.quantize import HALFTONES, PRINTER_DPI
from ...print_error import EVAL_RENDERS
from .fixed_fractions import parse_fixed

__all__ = ["PrintConfig", "load_inks", "iteration_seed", "RESUME_MAY_CHANGE", "config_conflicts", "SCHEDULES",
           "auto_eval_texels", "evaluation_count"]

#: the settings a resumed run may change: where it is, that it resumes, how long it runs, how often it saves and the
#: device it runs on (a checkpoint holds CPU tensors: a run started on a GPU resumes on the CPU and the other way)
RESUME_MAY_CHANGE = frozenset({"out", "resume", "iterations", "checkpoint_s", "device"})

#: the largest learning rate admitted: Adagrad's and Adam's first step moves each parameter of the mixture (a logit
#: under the sigmoid or softmax) by about lr, so at 100 it is already saturated (its gradients vanish)
MAX_LR = 100.0

#: the schedule of a run by the kind of its target, for the :class:`PrintConfig` fields left at None. Slabs: the
#: paper's 32 spp, with 300 iterations (a 20 mm ColorChecker slab takes seconds per iteration) and evaluations every
#: 50 at 128 spp: free of render noise (:mod:`torch_appearance.print_error`) they read the same as at 256 spp every 25
#: (the demo's final print 11.26 ± 0.08 and ± 0.05) at 0.14 of the job's time instead of 0.28. Objects: a textured
#: object's paths diffuse through its whole body; an iteration of Spot at 25 mm takes about 26 s at 8 spp on 2 cores.
#: Its error-against-time runs (``docs/bench_log.md``, "Object schedule") reached the same error at the same
#: time with 4 spp × 100 iterations as with 8 spp × 50 (quantised CIEDE2000 13.96 and 13.97, naive extrusion 15.76;
#: raw figures of 32-spp renders) and a worse one with lr 2 (15.49 against 14.59 at iteration 25); 45 iterations
#: at 8 spp keep a whole 25 mm job, with its naive baseline, evaluations and views, under 30 minutes (50 took 30.1).
#: An object's evaluations score a fixed random subset of ``eval_texels`` texels (the same for every evaluation and
#: every print of the run, so that comparisons are paired) at 128 spp: at 32 spp on all texels the estimate still
#: read 0.85 high on Spot at 10 mm (0.17 at 128) and the evaluations took 27 % of a 25 mm job. With 12,288 texels
#: they took 17.7 % of the default Spot 25 mm job (751 of 4,244 s; final print 8.56 ± 0.06, docs/bench_log.md); the
#: cost is linear in the texels, so 8,192 take about 12.5 % at 25 mm, at a sampling error of about 0.08 ΔE00 (in the
#: SE). But a smaller object's iterations are cheaper while its evaluations are not: 8,192 texels took 22 % of the
#: default Spot 10 mm job (318 of 1,435 s; 22,882 texels). So ``"auto"`` (:func:`auto_eval_texels`) sizes the subset
#: by the training: the evaluations render at most a quarter of the texel samples of the iterations, 2,048 to 8,192
#: texels (with a third, 4,290 texels, they still took 18.5 % of the 10 mm job: a quantised print's render also costs
#: about 0.75 s per call to prepare, whatever its texels). Camera views of the quantised object render at ``view_spp``. ``eval_texels`` 0: every texel.
SCHEDULES = {
    "slab": {"spp": 32, "iterations": 300, "eval_spp": 128, "eval_every": 50, "eval_texels": 0, "view_spp": 32},
    "object": {"spp": 8, "iterations": 45, "eval_spp": 128, "eval_every": 25, "eval_texels": "auto",
               "view_spp": 32},
}
#: bounds of ``eval_texels="auto"`` (:func:`auto_eval_texels`) and its share of the training's texel samples
AUTO_EVAL_TEXELS = (2048, 8192)
AUTO_EVAL_SAMPLE_SHARE = 1 / 4


#: the least time an iteration takes (the mixture, a render, the loss and the optimiser step of the smallest slab
#: take 5 ms on the development machine) and the longest job admitted: a count of iterations that cannot end within
#: a year even at that pace (``--iterations 10**12``) is refused before any work; the time of a job that starts is
#: logged once its first iteration has been timed
MIN_ITERATION_S = 1e-3
#: the most mixtures the naive baseline's table may hold (each is a render of a homogeneous slab: the default 6 steps
#: of 4 inks are 84, of 6 inks 462)
MAX_TABLE_ENTRIES = 20000
MAX_JOB_S = 365.25 * 86400


@dataclass
class PrintConfig:
    """Settings of one print optimisation run (every field is a flag of ta-optimize-print).

    Lengths in mm; ``dpi`` is the optimisation voxel pitch (300 DPI ≈ 0.0847 mm cubic voxels).

    Example:
        >>> cfg = PrintConfig(thickness_mm=1.0, dpi=300.0)
        >>> cfg.validate()
        >>> round(cfg.voxel_size, 4), cfg.depth
        (0.0847, 12)
    """
    target: str = "colorchecker"
    bottom_target: Optional[str] = None
    thickness_mm: float = 1.0
    dpi: float = 300.0
    width_mm: Optional[float] = None
    height_mm: Optional[float] = None
    inks: Sequence[str] = DEFAULT_INKS
    gamma: Tuple[float, float, float] = (1.0, 3.0, 1.0)
    spp: Optional[int] = None  # None: the schedule of the target's kind (SCHEDULES), also for the next three
    eval_spp: Optional[int] = None
    eval_every: Optional[int] = None
    iterations: Optional[int] = None
    eval_texels: Union[int, str, None] = None  # texels an evaluation scores, a random subset (0: all; objects: "auto")
    view_spp: Optional[int] = None  # objects: samples per pixel of the camera views (default 32)
    optimizer: str = "adagrad"
    lr: float = 1.0
    parameterization: str = "sigmoid"
    seed: int = 0
    gradient_seed: str = "same"  # "same": the replay retraces the forward's paths; "independent": seed_grad
    ior: Optional[float] = 1.5
    g: Optional[float] = None  # HG parameter; default: the inks' common g (0.4 for the built-in inks)
    printer_dpi: Tuple[float, float, float] = PRINTER_DPI
    table_steps: int = 6
    mesh: Optional[str] = None  # a textured mesh: optimise the object instead of a slab (height_mm: its z extent)
    texture: Optional[str] = None  # base-colour image for a mesh with UVs but no material
    shell_mm: float = 2.0  # objects: optimised depth below the surface; deeper voxels hold core_ink
    core_ink: str = "white"
    init: str = "naive"  # "naive": start from the naive extrusion; "white": 97 % white everywhere (the paper)
    estimator: str = "ema"  # "ema": loss gradient at the running mean of past renders; "plain": at this render
    ema_beta: float = 0.98  # decay of that running mean (about 1/(1 − β) renders)
    naive_baseline: bool = True  # score the naive extrusion (costs a table of homogeneous renders)
    remap_baseline: bool = False  # objects: also the 2.5D remapped baseline (a slab optimised in UV space)
    views: int = 3  # objects: camera renders of the quantised print from this many directions (0: none)
    view_size: int = 192  # objects: pixels per side of those renders
    halftone: str = "blue-noise"  # or "random" (independent draws, the paper): blue noise has less grain at the same
    # colour (docs/bench_log.md, "Halftoning"); a run recorded without this field was quantised at random
    printer: Optional[str] = None  # a printer profile (name or JSON path): its resolution, and a package at the end
    fixed: Sequence[str] = ()  # "INK=FRACTION:MASK" constraints (see pipelines.print.fixed_fractions)
    envmap: Optional[str] = None  # objects: a lat-long linear EXR (z up) lighting the print instead of uniform white
    out: str = "results/print"
    resume: bool = False
    checkpoint_s: float = 300.0  # write checkpoint.pt at least this often (wall seconds), besides every evaluation
    device: str = "cpu"  # where the iterations run: "cpu", "cuda" or "cuda:N" (the mixture, the renders, the loss and
    # the optimiser's state); evaluations render there too and are scored on the CPU; quantisation, its renders and
    # the files stay on the CPU

    def validate(self):
        """Raise ValueError/TypeError naming the field for anything out of range."""
        def positive(name, value, integer=False):
            ok = isinstance(value, int) if integer else isinstance(value, (int, float))
            if not ok or isinstance(value, bool):
                raise TypeError(f"{name}: expected {'an int' if integer else 'a number'}, got {type(value).__name__}")
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: expected > 0, got {value}")

        for name in ("thickness_mm", "dpi", "lr", "shell_mm", "checkpoint_s"):
            positive(name, getattr(self, name))
        if self.lr > MAX_LR:  # --lr 1e12 was taken: the first step saturated the mixture, then nothing moved
            raise ValueError(f"lr: expected at most {MAX_LR:g} (a step moves each of the mixture's parameters by "
                             f"about lr; at {MAX_LR:g} the first one already saturates it), got {self.lr:g}")
        check_device("device", self.device)
        for name in ("spp", "eval_spp", "eval_every", "iterations", "table_steps", "view_size", "view_spp"):
            if getattr(self, name) is not None or name not in SCHEDULES["slab"]:
                positive(name, getattr(self, name), integer=True)
        inks = self.inks.split(",") if isinstance(self.inks, str) else getattr(self.inks, "names", self.inks)
        n_inks = len(inks) if hasattr(inks, "__len__") else 0
        if isinstance(self.table_steps, int) and n_inks > 1:
            entries = math.comb(self.table_steps + n_inks - 1, n_inks - 1)
            if entries > MAX_TABLE_ENTRIES:  # --table-steps 10**12 ran without end (the table is listed, then rendered)
                raise ValueError(f"table_steps: {self.table_steps} steps give {entries:.3g} mixtures of the "
                                 f"{n_inks} inks, each rendered for the naive baseline's table; expected at most "
                                 f"{MAX_TABLE_ENTRIES} mixtures")
        texels = self.eval_texels
        if texels is not None and texels != "auto" and (isinstance(texels, bool) or not isinstance(texels, int) or
                                                         texels < 0 or 0 < texels < 1024):
            raise ValueError(f"eval_texels: expected 'auto', 0 (every texel) or an int >= 1024 (a random subset "
                             f"large enough for the mean's sampling error), got {texels!r}")
        if self.iterations is not None and self.iterations * MIN_ITERATION_S > MAX_JOB_S:
            raise ValueError(f"iterations: {self.iterations} iterations take at least "
                             f"{self.iterations * MIN_ITERATION_S / (365.25 * 86400):.3g} years (an iteration takes "
                             f"at least {MIN_ITERATION_S * 1e3:g} ms); expected a job under a year, at most "
                             f"{int(MAX_JOB_S / MIN_ITERATION_S)} iterations")
        if self.eval_spp is not None and self.eval_spp % EVAL_RENDERS:
            raise ValueError(f"eval_spp: expected a multiple of {EVAL_RENDERS} (an evaluation is {EVAL_RENDERS} "
                             f"independent renders of eval_spp/{EVAL_RENDERS} spp, from which the render noise is "
                             f"taken out of the error), got {self.eval_spp}")
        if isinstance(self.views, bool) or not isinstance(self.views, int) or self.views < 0:
            raise ValueError(f"views: expected an int >= 0, got {self.views!r}")
        for name in ("width_mm", "height_mm"):
            if getattr(self, name) is not None:
                positive(name, getattr(self, name))
        if self.gradient_seed not in ("same", "independent"):
            raise ValueError(f"gradient_seed: expected 'same' or 'independent', got {self.gradient_seed!r}")
        if self.init not in ("white", "naive"):
            raise ValueError(f"init: expected 'white' or 'naive', got {self.init!r}")
        if self.estimator not in ("ema", "plain"):
            raise ValueError(f"estimator: expected 'ema' or 'plain', got {self.estimator!r}")
        if isinstance(self.ema_beta, bool) or not isinstance(self.ema_beta, (int, float)) or \
                not 0.0 <= self.ema_beta < 1.0:
            raise ValueError(f"ema_beta: expected a number in [0, 1), got {self.ema_beta!r}")
        if self.optimizer not in ("adagrad", "adam"):
            raise ValueError(f"optimizer: expected 'adagrad' or 'adam', got {self.optimizer!r}")
        if self.ior is not None and (isinstance(self.ior, bool) or not isinstance(self.ior, (int, float))
                                     or not math.isfinite(self.ior) or self.ior < 1):  # nan reached the JSON writer
            raise ValueError(f"ior: expected a finite value >= 1, got {self.ior!r}")
        if len(tuple(self.gamma)) != 3 or min(self.gamma) < 0 or sum(self.gamma) <= 0:
            raise ValueError(f"gamma: expected three weights >= 0 with a positive sum, got {self.gamma!r}")
        if len(tuple(self.printer_dpi)) != 3 or min(self.printer_dpi) <= 0:
            raise ValueError(f"printer_dpi: expected three positive DPI values (x, y, z), got {self.printer_dpi!r}")
        if self.halftone not in HALFTONES:
            raise ValueError(f"halftone: expected one of {HALFTONES}, got {self.halftone!r}")
        if self.printer is not None:
            printer = load_printer(self.printer)
            if tuple(self.printer_dpi) != tuple(PRINTER_DPI) and not printer.matches(self.printer_dpi, 1e-6):
                raise ValueError(f"printer_dpi: {tuple(self.printer_dpi)} differs from the resolution of printer "
                                 f"{printer.name!r} {printer.dpi}; give one of them")
        if self.remap_baseline and self.mesh is None:
            raise ValueError("remap_baseline: the 2.5D remapped baseline is for objects (--mesh)")
        if self.mesh is not None:
            if self.height_mm is None:
                raise ValueError("height_mm: an object print needs the object's height in mm (--height-mm)")
            if self.envmap is not None and not os.path.isfile(self.envmap):
                raise ValueError(f"envmap: no such file {self.envmap!r}")
            if self.bottom_target is not None or self.width_mm is not None:
                raise ValueError("mesh: bottom_target and width_mm are slab settings; an object takes its colours "
                                 "from the mesh and its size from height_mm")
        if isinstance(self.fixed, str) or not isinstance(self.fixed, Sequence):
            raise TypeError(f"fixed: expected a sequence of INK=FRACTION:MASK strings, got {self.fixed!r}")
        for spec in self.fixed:
            parse_fixed(spec)
        if self.mesh is None and self.envmap is not None:
            raise ValueError("envmap: environment maps light object prints (--mesh); slabs use uniform light")
        if self.voxel_size > self.thickness_mm * 1.0001:
            raise ValueError(f"thickness_mm: expected at least one voxel ({self.voxel_size:.4f} mm), "
                             f"got {self.thickness_mm}")

    @classmethod
    def from_record(cls, record):
        """The config a run folder's ``config.json`` records (its other keys are ignored): tuples where the
        fields are tuples, and the inks as the run's own :class:`~torch_appearance.fabrication.Ink` records (their
        properties, not their names: a resumed run uses the inks it started with)."""
        if not isinstance(record, dict):
            raise TypeError(f"config: expected a dict (a run's config.json), got {type(record).__name__}")
        values = {f.name: record[f.name] for f in fields(cls) if f.name in record}
        values.setdefault("halftone", "random")  # runs from before the option were quantised at random
        values.setdefault("eval_texels", 0)  # and scored every texel,
        values.setdefault("view_spp", values.get("eval_spp"))  # their views at the evaluations' spp
        for name in ("gamma", "printer_dpi", "fixed"):
            if isinstance(values.get(name), list):
                values[name] = tuple(values[name])
        if isinstance(values.get("inks"), list):
            values["inks"] = tuple(ink_from_dict(ink, f"config.json: inks[{k}]") if isinstance(ink, dict) else ink
                                   for k, ink in enumerate(values["inks"]))
        return cls(**values)

    @property
    def kind(self):
        """``"object"`` with a mesh, else ``"slab"``: the key of its defaults in :data:`SCHEDULES`."""
        return "slab" if self.mesh is None else "object"

    def resolved(self):
        """This config with the schedule fields left at None (``spp``, ``iterations``, ``eval_spp``,
        ``eval_every``, ``eval_texels``, ``view_spp``) set to the defaults of its kind (:data:`SCHEDULES`); the run records these.

        Example:
            >>> PrintConfig().resolved().spp, PrintConfig(mesh="spot.obj", height_mm=25).resolved().spp
            (32, 8)
        """
        fill = {name: value for name, value in SCHEDULES[self.kind].items() if getattr(self, name) is None}
        if self.printer is not None:
            dpi = load_printer(self.printer).dpi
            if tuple(self.printer_dpi) != dpi:
                fill["printer_dpi"] = dpi
        return dataclasses.replace(self, **fill) if fill else self

    @property
    def voxel_size(self):
        return 25.4 / self.dpi

    @property
    def depth(self):
        return max(1, int(round(self.thickness_mm / self.voxel_size)))

    def phase_g(self, inks):
        """The Henyey–Greenstein g of the run: ``g`` when set, else the inks' common g (ValueError if they
        disagree)."""
        return inks.g if self.g is None else self.g


def evaluation_count(cfg):
    """The evaluations of a run of resolved ``cfg``: the start, one every ``eval_every`` iterations and the last,
    the naive baseline, the 2.5D remapped baseline and the final print (quantised)."""
    within = cfg.iterations // cfg.eval_every + (1 if cfg.iterations % cfg.eval_every else 0)
    return 1 + within + int(bool(cfg.naive_baseline)) + int(bool(cfg.remap_baseline)) + 1


def auto_eval_texels(texels, cfg):
    """The texels an evaluation of a resolved ``cfg`` with ``eval_texels="auto"`` scores, for an object of
    ``texels`` texels: as many as keep the evaluations' texel samples (:func:`evaluation_count` × M × ``eval_spp``)
    at :data:`AUTO_EVAL_SAMPLE_SHARE` of the iterations' (``iterations`` × ``texels`` × ``spp``), within
    :data:`AUTO_EVAL_TEXELS`; 0 (every texel) when that is all of them.

    Example:
        >>> cfg = PrintConfig(mesh="spot.obj", height_mm=10).resolved()
        >>> auto_eval_texels(22882, cfg), auto_eval_texels(145615, cfg), auto_eval_texels(1500, cfg)
        (3218, 8192, 0)
    """
    low, high = AUTO_EVAL_TEXELS
    budget = AUTO_EVAL_SAMPLE_SHARE * cfg.iterations * texels * cfg.spp / (evaluation_count(cfg) * cfg.eval_spp)
    count = int(min(high, max(low, round(budget))))
    return 0 if count >= texels else count


def load_inks(spec):
    """An :class:`~torch_appearance.fabrication.InkSet` from ink names (a list or a comma-separated string), a JSON
    ink file, or :class:`~torch_appearance.fabrication.Ink` records (a resumed run's, :meth:`PrintConfig.from_record`)."""
    if isinstance(spec, InkSet):
        return spec
    if isinstance(spec, str):
        if spec.lower().endswith(".json"):
            return InkSet.load_json(spec)
        spec = [s.strip() for s in spec.split(",") if s.strip()]
    spec = list(spec)
    if spec and all(isinstance(ink, Ink) for ink in spec):
        return InkSet(spec)
    return InkSet.from_names(spec)


def iteration_seed(seed, iteration):
    """A distinct 63-bit seed per iteration (SplitMix64 of the run seed and the iteration)."""
    z = (int(seed) * 0x9E3779B97F4A7C15 + int(iteration) + 1) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return (z ^ (z >> 31)) >> 1


def _plain(value):
    """Tuples and lists alike, ink sets as their properties: the form in which two settings are compared."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Ink):
        return _plain(list(dataclasses.astuple(value)))
    return value


def config_conflicts(stored, mine, names=None):
    """``[(field, mine, stored)]`` for the fields (``names``, default all but :data:`RESUME_MAY_CHANGE`) where two
    :class:`PrintConfig` disagree; inks are compared by their properties (``load_inks`` of each)."""
    names = [f.name for f in fields(PrintConfig) if f.name not in RESUME_MAY_CHANGE] if names is None else names
    out = []
    for name in names:
        a, b = getattr(mine, name), getattr(stored, name)
        if name == "inks":
            same = _plain(list(load_inks(a))) == _plain(list(load_inks(b)))
        else:
            same = _plain(a) == _plain(b)
        if not same:
            out.append((name, a, b))
    return out
