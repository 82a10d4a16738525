"""Print appearance optimisation (Nindel et al., TOG 2021): the loop as a library function.

Given a print target (a slab's face images, :class:`.SlabTarget`, or a textured object's surface texels,
:class:`.ObjectTarget`), find per-voxel ink mixtures whose rendered (= predicted printed) look matches it, quantise
to the printer's native resolution, and write a run folder (see :func:`optimize_print`). The loop only calls the
target's methods (render, appearance, scores, baselines, outputs); it never asks which kind it holds.

Data flow: ``MaterialMixture`` (learnable logits, N × D × H × W) → (σ_t, albedo) → ``target.render`` (C++ path
tracer through :class:`~torch_appearance.nn.SceneRenderer`, radiative backpropagation) → ``target.appearance``
(E1 ΔE76², E2 3D SSIM, E3 3D Sobel) → ``loss.backward()`` → Adagrad/Adam step. Every ``eval_every`` iterations
the print is scored with CIEDE2000 free of the render's Monte Carlo noise: four independent renders of ``eval_spp / 4``
spp with fixed seeds, extrapolated to infinitely many samples (:mod:`torch_appearance.print_error`); an object's
evaluations render and score a fixed random subset of ``eval_texels`` texels (the sampling error is in the standard
errors), its final print and naive baseline are also rendered whole as pictures. After the loop:
probabilistic quantisation (one ink per printer micro-voxel) and the same evaluation of the *quantised* volume at the
printer resolution; the baselines are scored the same way.

Devices (``cfg.device``): the mixture's parameters, the optimiser's state, the renders, the loss and its target, the
running mean and every other tensor of an iteration live on the run's device; the loop's own code reads back one
thing per iteration, its log row (the loss and its three parts, one transfer: :func:`log_values`). (What it calls
still waits on the device where it checks its input: the tracer's front door builds each render's scene on the host,
the appearance loss refuses non-finite colours and an empty mask.) Evaluations render on the device and are scored on
the CPU (the renders are moved there explicitly); the naive baseline, the quantisation, the quantised print's
renders, the figures and the files stay on the CPU. A checkpoint holds CPU tensors, so a run resumes on another
device.
"""
import dataclasses
import os
import time

import numpy as np
import torch

from ... import distributed
from ... import io as ta_io
from ...fabrication.export import export_slices, save_index_volume
from ...fabrication.printer import load_printer
from ...nn.losses import AppearanceLoss
from ...nn.mixture import MaterialMixture
from .baselines import quantize
from .config import PrintConfig, auto_eval_texels, config_conflicts, iteration_seed, load_inks
from .fixed_fractions import fixed_fractions
from .object_target import ObjectTarget
from .remap25d import MAX_SLAB_TEXELS, prepare_uv_slab, wrap_slab_weights
from .report import write_figures
from ..runs import RunInterrupted, check_run_folder_owner, claim_run_folder, load_checkpoint, sigint_deferred
from ...print_error import EVAL_RENDERS
from ...progress import progress_bar
from .run_folder import CHECKPOINT, LOG_FIELDS, npz_bytes, save_torch, score
from .slab_target import SlabTarget

__all__ = ["optimize_print", "build_target", "remap_baseline"]


def build_target(cfg: PrintConfig, log=print):
    """The print target of ``cfg`` (a :class:`SlabTarget`, or with ``cfg.mesh`` an :class:`ObjectTarget`), to share
    between runs that differ only in inks or optimiser settings (``optimize_print(cfg, target=...)``)."""
    cfg.validate()
    cfg = cfg.resolved()
    inks = load_inks(cfg.inks)
    _check_core_ink(cfg, inks)
    return (SlabTarget if cfg.mesh is None else ObjectTarget).from_config(cfg, inks, log)


def _check_core_ink(cfg, inks):
    if cfg.mesh is not None and cfg.core_ink.lower() not in [n.lower() for n in inks.names]:
        raise ValueError(f"core_ink: {cfg.core_ink!r} is not in the ink set {list(inks.names)}")


def optimize_print(cfg: PrintConfig, progress=True, log=print, target=None):
    """Run one print optimisation of a slab or, with ``cfg.mesh``, of a textured object, and write ``cfg.out``.

    Run folder (fixed names other tools rely on): ``config.json``; ``log.csv`` (:data:`.run_folder.LOG_FIELDS`:
    iteration, wall_s, loss, E1, E2, E3 — the loss whose gradient the step took: with the ``ema`` estimator that of
    the running mean of the renders before the step's own (rows 1 and 2 both hold the first render's), else of the
    step's render; at evaluations the error free of render noise ``dE00_mean`` ±
    ``dE00_mean_se``, ``dE00_p95`` ± ``dE00_p95_se``, ``dE76_rms``, the evaluation render's raw ``dE00_mean_raw``,
    ``dE00_p95_raw``, ``dE76_mean_raw`` and its noise ``dE00_noise``; seed); ``convergence.png``;
    ``ink_usage_by_depth.png``; the texel colours of ``target``, ``baseline`` (naive extrusion, quantised),
    ``initial``, ``optimized`` (continuous mixture) and ``final`` (quantised result; the means of their evaluation
    renders): for a slab linear-RGB ``.exr`` images of the top face with PNG previews (and
    ``*_bottom`` for two-sided targets) and ``dE00_heatmap.png``; for an object ``.npy`` (N, 3) linear RGB and a
    coloured point cloud ``.ply`` at the texels' surface points, and ``object.npz`` (the voxelisation);
    ``mixture.npz`` (weights N×D×H×W, ink names, voxel size); ``quantized.npz`` (uint8 material indices at the
    printer resolution, 255 = void outside an object); ``slices/`` (one PNG per printer layer +
    ``palette.json``); ``checkpoint.pt`` (written atomically at every evaluation, after ``cfg.checkpoint_s`` seconds
    without one, and on Ctrl-C; ``cfg.resume`` continues from it with the settings of ``config.json``, of which only
    :data:`.config.RESUME_MAY_CHANGE` may differ); ``summary.json``. The folder is locked while the run writes to it
    (:func:`~torch_appearance.pipelines.runs.claim_run_folder`): a second run on it is refused, and so is a folder of
    another tool; ``tool.json`` names this one.

    Args:
        cfg: the settings. progress: show a progress bar (whole lines when stderr is not a terminal).
        log: where one-line messages go.
        target: optional prebuilt target from :func:`build_target` for the same geometry settings (a run with
            other inks or optimiser settings reuses the voxelisation and the scene).

    Returns:
        The summary dict (also written to ``summary.json``).

    Raises:
        ValueError, TypeError: bad settings or inputs, a folder that holds another run or is locked by one, a slab
            too large for this machine's memory; all before the run folder is written.
        RunInterrupted: (a ``KeyboardInterrupt``) Ctrl-C during the optimisation, after the checkpoint was written.
    """
    t_call = time.perf_counter()
    cfg.validate()
    cfg = cfg.resolved()  # the schedule of its kind for what it leaves at None; config.json records these
    _check_device_usable(cfg.device)
    rank, world = distributed.rank_and_world()
    folder = cfg.out
    ckpt_path = os.path.join(folder, CHECKPOINT)
    _check_not_a_run(cfg, ckpt_path)
    inks = load_inks(cfg.inks)
    if cfg.printer is not None:
        load_printer(cfg.printer).material_indices(inks.names)  # an ink the printer lacks: refused before the run
    if cfg.g is None:
        inks.g  # noqa: B018 - raises ValueError if the inks disagree on g
    if target is None:
        target = build_target(cfg, log)
    else:
        _check_core_ink(cfg, inks)
    target.use(inks, cfg)  # the run's inks (their g) and settings
    constraints, fixed = fixed_fractions(target, cfg.fixed, inks)
    if rank != 0:
        # under torchrun every rank runs the same loop (the renders are collective); only rank 0 writes the run
        # folder, the others write to a private temporary one that is removed at the end
        import tempfile
        folder = tempfile.mkdtemp(prefix=f"optimize_print_rank{rank}_")
        progress, log = False, (lambda *args, **kwargs: None)
        try:
            return _Run(cfg, target, inks, constraints, fixed, folder, ckpt_path, log, world, t_call).run(progress)
        finally:
            import shutil
            shutil.rmtree(folder, ignore_errors=True)
    # the folder is made only once the inputs are known to be good (no partial run folder), and locked while the run
    # writes to it: a second run on the same folder is refused instead of mixing its files with this one's, and so
    # is another tool's folder (claim_run_folder marks it as this tool's)
    with claim_run_folder(folder, TOOL):
        _check_not_a_run(cfg, ckpt_path)  # again under the lock: another run may have finished in the meantime
        return _Run(cfg, target, inks, constraints, fixed, folder, ckpt_path, log, world, t_call).run(progress)


#: the iterations whose mean time is compared with the pace last logged, and the change of pace logged again
PACE_WINDOW = 10
PACE_CHANGE = 1.5
#: seconds of a run's results besides the quantised print's renders (figures, slices, files), measured 2.1 s on a
#: 64² slab and 2.0 s on a ColorChecker on the development machine
RESULTS_S = 2.0


def job_estimate(iterations, done, eval_every, step_s, evaluation_s, results_s):
    """Seconds the rest of a run takes at ``step_s`` seconds per iteration, ``evaluation_s`` per evaluation and
    ``results_s`` for its results: the iterations after ``done``, their evaluations (every ``eval_every`` and at the
    end) and the results; with the text that says so (the views of an object are not counted).

    Example:
        >>> job_estimate(300, 2, 50, 0.5, 2.0, 4.0)
        (165.0, '298 iterations of 0.5 s, 6 evaluations of 2 s, the results 4 s')
    """
    left = iterations - done
    evaluations = iterations // eval_every - done // eval_every + (1 if iterations % eval_every else 0)
    total = left * step_s + evaluations * evaluation_s + results_s
    return total, (f"{left} iterations of {step_s:.2g} s, {evaluations} evaluations of {evaluation_s:.2g} s, the "
                   f"results {results_s:.2g} s")


def duration_text(seconds):
    """``seconds`` in the unit a person reads: s, min, h, days or years.

    Example:
        >>> [duration_text(s) for s in (42, 600, 7200, 3 * 86400, 1e12)]
        ['42 s', '10 min', '2 h', '3 days', '3.2e+04 years']
    """
    for unit, size in (("years", 365.25 * 86400), ("days", 86400), ("h", 3600), ("min", 60)):
        if seconds >= 2 * size:
            return f"{seconds / size:.2g} {unit}"
    return f"{seconds:.2g} s"


def _scores_text(scores):
    """``mean ± SE/p95`` of a score dict (the SE left out where there is none)."""
    se = scores.get("dE00_mean_se")
    se_text = "" if se is None or se != se else f" ± {se:.2f}"
    return f"{scores['dE00_mean']:.2f}{se_text}/{scores['dE00_p95']:.2f}"


#: the tool that owns a print run's folder (:func:`~torch_appearance.pipelines.runs.claim_run_folder`)
TOOL = "ta-optimize-print"


def _check_device_usable(device):
    """A ``device`` where tensors cannot be rendered (:func:`~torch_appearance.render.cuda_launch.device_unusable`):
    ValueError naming ``device``, before any work."""
    from ...render.cuda_launch import device_unusable

    why = device_unusable(device)
    if why:
        raise ValueError(f"device: {why}; use device='cpu'")


def _to_cpu(value):
    """``value`` (a state dict, nested dicts, lists and tuples of tensors) with its tensors on the CPU (a CPU tensor
    itself, not a copy): what a checkpoint holds, whichever device the run is on."""
    if isinstance(value, torch.Tensor):
        return value.cpu()
    if isinstance(value, dict):
        return {k: _to_cpu(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_to_cpu(v) for v in value)
    return value


def _check_not_a_run(cfg, ckpt_path):
    check_run_folder_owner(cfg.out, TOOL)
    if os.path.exists(ckpt_path) and not cfg.resume:
        raise ValueError(f"out: {cfg.out!r} already holds a run (checkpoint.pt); pass resume=True (--resume) to "
                         f"continue it or choose another folder")


def remap_baseline(target, inks, cfg, *, work_dir, log=print, progress=False, max_texels=MAX_SLAB_TEXELS):
    """The 2.5D remapped baseline of an object print (thesis part II §3.2): a slab in the mesh's UV space
    (:func:`.remap25d.prepare_uv_slab`) optimised by this loop in ``work_dir/slab`` and wrapped around the object
    (:func:`.remap25d.wrap_slab_weights`).

    Returns:
        ((N, D, H, W) float32 weights on the object's grid, info dict: the slab-size numbers, the slab run's folder,
        target, seconds and CIEDE2000, remap counts and seconds).
    """
    t0 = time.perf_counter()
    slab_cfg, info = prepare_uv_slab(target, cfg, work_dir=work_dir, log=log, max_texels=max_texels)
    summary = optimize_print(slab_cfg, progress=progress, log=log)
    with np.load(os.path.join(slab_cfg.out, "mixture.npz")) as data:
        slab_weights = data["weights"]
        names = [str(x) for x in data["inks"]]
    if names != list(inks.names):
        raise ValueError(f"slab run: its mixture is for inks {names}, this run has {list(inks.names)}")
    info.update(slab_dir=slab_cfg.out, uv_target=slab_cfg.target, slab_s=time.perf_counter() - t0,
                slab_final_dE00_mean=summary["final_quantized"]["dE00_mean"])
    weights, remap_info = wrap_slab_weights(target, slab_weights, inks, cfg.core_ink, window=info["window"], log=log)
    info.update(remap_info)
    return weights, info


def log_values(loss, parts):
    """``{"loss", "E1", "E2", "E3"}`` as Python floats from the 0-dim tensors ``loss`` and ``parts`` (a dict), read
    back from their device in one transfer (``Tensor.tolist`` of their stack): the one host round trip of an
    iteration.

    Example:
        >>> log_values(torch.tensor(1.5), {"E1": torch.tensor(0.5), "E2": torch.tensor(1.0)})
        {'loss': 1.5, 'E1': 0.5, 'E2': 1.0}
    """
    names = ["loss", *parts]
    values = torch.stack([loss.detach(), *(v.detach() for v in parts.values())]).tolist()
    return dict(zip(names, values))


class _Run:
    """One run of :func:`optimize_print` once its inputs are checked: the model, the optimiser and the log rows,
    with the steps (start or resume, baselines, iterations, results) as methods; writes to ``folder``."""

    def __init__(self, cfg, target, inks, constraints, fixed, folder, ckpt_path, log, world, t_call):
        self.t_call = t_call  # perf_counter() when optimize_print was called: the summary's job_s
        self.cfg, self.target, self.inks, self.fixed = cfg, target, inks, fixed
        self.folder, self.ckpt_path, self.log, self.world = folder, ckpt_path, log, world
        self.shape = tuple(target.shape)
        self.device = torch.device(cfg.device)
        self.model = MaterialMixture(inks, self.shape, parameterization=cfg.parameterization, support=target.support,
                                     core_ink=cfg.core_ink if target.support is not None else None,
                                     fixed=constraints).to(self.device)
        optim_cls = torch.optim.Adagrad if cfg.optimizer == "adagrad" else torch.optim.Adam
        self.optimizer = optim_cls(self.model.parameters(), lr=cfg.lr)
        self.criterion = AppearanceLoss(gamma=tuple(cfg.gamma))
        self.rows, self.start, self.wall_offset = [], 0, 0.0
        self.ema = {"sum": None, "count": 0}  # estimator "ema": running mean of the renders (checkpointed)
        self.baseline, self.remap = None, None
        self.evaluated = (None, None)  # (iteration, renders) of the latest evaluation
        self.eval_seed = iteration_seed(cfg.seed, -1)
        # an evaluation: EVAL_RENDERS independent renders of eval_spp / EVAL_RENDERS spp with these seeds
        self.eval_seeds = [iteration_seed(self.eval_seed, k) for k in range(EVAL_RENDERS)]
        self.eval_seconds = 0.0  # spent on evaluations (renders and scores) by this call: the summary's evaluation
        self.picture_seconds = 0.0  # spent on whole pictures of prints scored on a subset (:meth:`picture`)
        # an object's evaluations score a fixed random subset of its texels (None: all), the same for every print
        count = cfg.eval_texels
        if count == "auto" and not isinstance(target, ObjectTarget):
            count = 0  # a slab is scored whole
        elif count == "auto":
            count = auto_eval_texels(len(target.target), cfg)
            log(f"optimize_print: evaluations score {'every texel' if not count else f'{count} random texels'} of "
                f"{len(target.target)} (eval_texels 'auto': a quarter of the iterations' texel samples at most)")
        self.subset = target.evaluation_subset(count, iteration_seed(cfg.seed, -3))
        self.eval_scene = None if self.subset is None else target.subset_scene(self.subset)
        self.quant_seed = iteration_seed(cfg.seed, -2)
        self.evaluation_s = None  # seconds of the start's evaluation (renders and scores), when this call made it
        self.quantised_s = None  # seconds of the naive baseline's quantisation and renders, when this call made them

    def run(self, progress):
        resuming = self.cfg.resume and os.path.exists(self.ckpt_path)
        if resuming:
            self.check_resumed_settings()  # before config.json is rewritten
        self.write_inputs()
        if resuming:
            self.resume()
        if not self.rows:
            self.start_fresh()
        if self.cfg.remap_baseline and self.remap is None:
            try:
                self.remap = self.remap_baseline()
            except RunInterrupted as stop:  # the UV slab's own run: it is resumed through this one
                raise RunInterrupted(f"interrupted in the 2.5D remapped baseline's slab run ({stop.folder}, its "
                                     f"checkpoint at iteration {stop.iteration}); continue this run with --resume "
                                     f"(Python: resume=True)", self.folder, 0) from None
        self.iterate(progress)
        try:
            return self.finish()
        except KeyboardInterrupt:
            raise RunInterrupted(f"interrupted while writing the results of all {self.cfg.iterations} iterations; "
                                 f"the checkpoint is in {self.folder}; --resume (Python: resume=True) writes them "
                                 f"again", self.folder, self.cfg.iterations) from None

    # ---------------------------------------------------------------------------------------------- helpers
    def renders(self, render):
        """(K, *texels) the K = :data:`EVAL_RENDERS` independent renders of an evaluation: ``render(spp, seed)``
        with ``eval_spp / K`` spp and the evaluation's seeds, on the CPU (where they are scored)."""
        t0 = time.perf_counter()
        spp = self.cfg.eval_spp // EVAL_RENDERS
        renders = torch.stack([render(spp, seed).cpu() for seed in self.eval_seeds])
        self.eval_seconds += time.perf_counter() - t0
        return renders

    def evaluate(self):
        """(K, *texels) evaluation renders of the current continuous mixture."""
        with torch.no_grad():
            s, a = self.model()
            subset = {} if self.eval_scene is None else {"scene": self.eval_scene}
            return self.renders(lambda spp, seed: self.target.render(s, a, spp, seed, **subset))

    def score(self, renders, texels=False, against=None):
        """The scores (:func:`.run_folder.score`) of evaluation ``renders`` (K, *texels) on the target's scored
        texels (``target.scored``; an object's evaluation subset, with its sampling error in the SE): against the
        target, or against the evaluation renders ``against`` of another print (both free of render noise)."""
        t0 = time.perf_counter()
        scored = [self.target.scored(r, self.subset) for r in renders]
        reference = scored[0][1] if against is None else \
            torch.stack([self.target.scored(r, self.subset)[0] for r in against])
        population = None if self.subset is None else len(self.target.target)
        result = score(torch.stack([p for p, _ in scored]), reference, texels=texels, population=population)
        self.eval_seconds += time.perf_counter() - t0
        return result

    def loss_row(self, texels):
        with torch.no_grad():
            loss, parts = self.target.appearance(self.criterion, texels)
        return {"loss": float(loss), **{k: float(v) for k, v in parts.items()}}

    def quantized(self, weights, fixed=()):
        """Printer-resolution indices of ``weights``, the print prepared for rendering (``target.prepare_quantized``:
        prepared once for its evaluation renders, picture and views) and its evaluation renders (K, *texels)."""
        indices = quantize(self.target, weights, self.inks, self.cfg, self.quant_seed, fixed)
        t0 = time.perf_counter()
        prepared = self.target.prepare_quantized(indices, self.cfg.printer_dpi)
        self.eval_seconds += time.perf_counter() - t0
        subset = {} if self.eval_scene is None else {"sensor": self.eval_scene.sensor}
        return indices, prepared, self.renders(lambda spp, seed: self.target.render_quantized(
            prepared, self.inks, self.cfg.printer_dpi, spp, seed, **subset))

    def picture(self, indices, renders):
        """(*texels) the colours to save as the picture of a quantised print (``indices``, or as prepared) with
        evaluation ``renders``: their mean where they cover every texel, else one render of every texel at the
        training's spp (the print is scored on the subset; the picture is for looking at)."""
        if self.subset is None:
            return renders.mean(0)
        t0 = time.perf_counter()
        image = self.target.render_quantized(indices, self.inks, self.cfg.printer_dpi, self.cfg.spp,
                                             iteration_seed(self.eval_seed, EVAL_RENDERS))
        self.picture_seconds += time.perf_counter() - t0
        return image

    # ---------------------------------------------------------------------------------------------- steps
    def write_inputs(self):
        cfg, target = self.cfg, self.target
        ta_io.write_json(os.path.join(self.folder, "config.json"), {
            **dataclasses.asdict(cfg), "inks": [dataclasses.asdict(i) for i in self.inks],
            "voxel_size_mm": cfg.voxel_size, "kind": target.kind, **target.describe(), "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(), "ranks": self.world, **target.inputs()})
        target.save_inputs(self.folder)
        target.save_texels(self.folder, "target", target.target)

    def resume(self):
        state = load_checkpoint(self.ckpt_path)
        if state["iteration"] > self.cfg.iterations:
            raise ValueError(f"iterations: the checkpoint in {self.folder!r} is at iteration {state['iteration']}; "
                             f"expected at least that many, got {self.cfg.iterations}")
        if tuple(state["grid_dhw"]) != self.shape or state["inks"] != list(self.inks.names):
            raise ValueError(f"resume: the checkpoint in {self.folder!r} is for grid {state['grid_dhw']} and inks "
                             f"{state['inks']}, this run has {list(self.shape)} and {list(self.inks.names)}")
        self.model.load_state_dict(state["model"])  # copied onto the model's device; the optimiser's state follows
        self.optimizer.load_state_dict(state["optimizer"])  # its parameters' device
        self.rows, self.start, self.wall_offset = state["rows"], state["iteration"], state["wall_s"]
        ema = state.get("ema", self.ema)
        self.ema = {**ema, "sum": None if ema["sum"] is None else ema["sum"].to(self.device)}
        self.baseline, self.remap = state["baseline"], state.get("baseline_remap")
        self.log(f"optimize_print: resuming {self.folder} at iteration {self.start}")

    def check_resumed_settings(self):
        """A resumed run must have the settings it started with (:data:`.config.RESUME_MAY_CHANGE` aside)."""
        path = os.path.join(self.cfg.out, "config.json")
        if not os.path.isfile(path):
            return
        stored = PrintConfig.from_record(ta_io.read_json(path, name="config.json"))
        differ = config_conflicts(stored, self.cfg)
        if differ:
            raise ValueError("resume: the run in " + repr(self.cfg.out) + " was made with other settings: " +
                             "; ".join(f"{name} {mine!r} (the run has {theirs!r})" for name, mine, theirs in differ))

    def start_fresh(self):
        """The naive extrusion, quantised and scored the same way as the result; the warm start; row 0."""
        cfg, target = self.cfg, self.target
        base_w = None
        if cfg.naive_baseline:
            t0 = time.perf_counter()
            base_w, table = target.naive_weights(self.inks, cfg)
            t_quantised = time.perf_counter()
            _, base_print, base_renders = self.quantized(base_w)
            picture = self.picture(base_print, base_renders)
            self.quantised_s = time.perf_counter() - t_quantised  # the time estimate's cost of the final print
            self.baseline = {"image": picture.numpy(), **self.score(base_renders), "table": table,
                             "seconds": time.perf_counter() - t0}
            target.save_texels(self.folder, "baseline", self.baseline["image"])
            del base_print
        if cfg.init == "naive":  # warm start: the optimisation begins where the naive extrusion ends
            self.model.set_weights(target.naive_weights(self.inks, cfg)[0] if base_w is None else base_w)
        # the extrusion's (inks, D, H, W) weights are not kept through the optimisation (1.16 GB for Spot at 40 mm)
        del base_w
        t0 = time.perf_counter()
        initial = self.evaluate()
        target.save_texels(self.folder, "initial", initial.mean(0), self.subset)
        # the appearance loss needs every texel (its filters see neighbours): on a subset, row 0 takes the loss of
        # the first iteration's render, which is of this same state (:meth:`iterate`)
        loss = self.loss_row(initial.mean(0)) if self.subset is None else {}
        self.rows.append({"iteration": 0, "wall_s": 0.0, **loss, **self.score(initial), "seed": self.eval_seed})
        self.evaluation_s = time.perf_counter() - t0  # the time estimate's cost of an evaluation

    def remap_baseline(self):
        """The 2.5D remapped baseline (:func:`remap_baseline`), quantised and scored as the result."""
        t0 = time.perf_counter()
        weights, info = remap_baseline(self.target, self.inks, self.cfg,
                                       work_dir=os.path.join(self.folder, "remap25d"), log=self.log)
        _, remap_print, renders = self.quantized(weights, self.fixed)
        remap = {"image": self.picture(remap_print, renders).numpy(), **self.score(renders), "info": info,
                 "seconds": time.perf_counter() - t0}
        self.target.save_texels(self.folder, "baseline_remap", remap["image"])
        return remap

    def step(self, seed, record):
        """One optimiser step on a render with ``seed``. Ctrl-C may stop it anywhere before the step is applied,
        leaving the state of the iteration before; the step, the running mean and ``record(loss, parts)`` (the log
        row) are applied together, with Ctrl-C held back."""
        cfg = self.cfg
        sigma_t, albedo = self.model()
        ema = None
        if cfg.estimator == "ema":
            # the loss's gradient with respect to the texel colours is taken at the running mean of the past
            # renders and applied to this render: the adjoint no longer shares this render's noise (that
            # correlation biases the plain estimator at low spp towards less noisy, not more accurate, media).
            # From the second iteration on that mean is known before the render, and so is the adjoint: one walk
            # then gives the render and its gradient (render_scene's ``adjoint``).
            old = self.ema

            def adjoint_at(primal):
                x = primal.clone().requires_grad_(True)
                loss, parts = self.target.appearance(self.criterion, x)
                return torch.autograd.grad(loss, x)[0], loss, parts

            if old["count"] == 0:
                image = self.target.render(sigma_t, albedo, cfg.spp, seed)
                adjoint, loss, parts = adjoint_at(image.detach())
            else:
                adjoint, loss, parts = adjoint_at(old["sum"] / (1.0 - cfg.ema_beta ** old["count"]))
                image = self.target.render(sigma_t, albedo, cfg.spp, seed, adjoint=adjoint)
            now = image.detach()
            ema = {"sum": (1.0 - cfg.ema_beta) * now + (0.0 if old["sum"] is None else cfg.ema_beta * old["sum"]),
                   "count": old["count"] + 1}
            surrogate = (adjoint * image).sum()
        else:
            image = self.target.render(sigma_t, albedo, cfg.spp, seed)
            loss, parts = self.target.appearance(self.criterion, image)
            surrogate = loss
        self.optimizer.zero_grad(set_to_none=True)
        surrogate.backward()
        # the full (3, D, H, W) grids of this iteration (1.4 GB for Spot at 40 mm) are not kept alive through the
        # evaluations, the quantisation and the next iteration's mixture
        del sigma_t, albedo, image, surrogate
        with sigint_deferred():
            self.optimizer.step()
            if ema is not None:
                self.ema = ema
            record(loss, parts)

    def checkpoint(self, iteration, wall_s):
        """``checkpoint.pt`` (its tensors on the CPU: it resumes on any device) and ``log.csv``."""
        save_torch({"model": _to_cpu(self.model.state_dict()), "optimizer": _to_cpu(self.optimizer.state_dict()),
                    "rows": self.rows, "iteration": iteration, "wall_s": wall_s, "baseline": self.baseline,
                    "baseline_remap": self.remap, "ema": _to_cpu(self.ema),
                    "grid_dhw": list(self.shape), "inks": list(self.inks.names)},
                   os.path.join(self.folder, CHECKPOINT))
        ta_io.write_csv(os.path.join(self.folder, "log.csv"), self.rows, LOG_FIELDS)

    def iterate(self, progress):
        """The optimisation from ``self.start``: a checkpoint at every evaluation, after ``cfg.checkpoint_s``
        seconds of wall time without one, and on Ctrl-C (then :class:`~torch_appearance.pipelines.runs.RunInterrupted`
        says how to resume)."""
        cfg = self.cfg
        bar = progress_bar(total=cfg.iterations, initial=self.start, disable=not progress, desc="optimize_print",
                           unit="it")
        t_start = time.perf_counter() - self.wall_offset
        last_eval = self.rows[-1] if self.rows else {}
        last_checkpoint = time.perf_counter()
        done = self.start

        def record(loss, parts):
            nonlocal done
            values = log_values(loss, parts)  # the iteration's one read back from the device
            if done == 0 and "loss" not in self.rows[0]:  # scored on a subset: the loss of the same state
                self.rows[0].update(values)
            self.rows.append({"iteration": done + 1, **values, "seed": seed,
                              "wall_s": time.perf_counter() - t_start})
            done += 1

        # the iteration whose time is logged with the whole job's: with the ``ema`` estimator the first iteration
        # of a fresh run walks twice (its adjoint needs its own render), the later ones once
        timed = self.start + (1 if cfg.estimator == "ema" and self.ema["count"] == 0 else 0)
        try:
            for it in range(self.start, cfg.iterations):
                seed = iteration_seed(cfg.seed, it)
                t_step = time.perf_counter()
                self.step(seed, record)
                step_s = time.perf_counter() - t_step
                if it == timed or (it + 1 == cfg.iterations and it < timed):
                    pace, window = self.log_estimate(it + 1, step_s), []
                elif it > timed:  # the paths change with the mixture: a pace that moved by half is logged again
                    window.append(step_s)
                    if len(window) == PACE_WINDOW:
                        mean = sum(window) / PACE_WINDOW
                        if not 1 / PACE_CHANGE < mean / pace < PACE_CHANGE:
                            pace = self.log_estimate(it + 1, mean, PACE_WINDOW)
                        window = []
                row = self.rows[-1]
                if (it + 1) % cfg.eval_every == 0 or it + 1 == cfg.iterations:
                    renders = self.evaluate()
                    row.update(self.score(renders))
                    self.evaluated = (done, renders)
                    row["wall_s"] = time.perf_counter() - t_start
                    last_eval = row
                if "dE00_mean" in row or time.perf_counter() - last_checkpoint > cfg.checkpoint_s:
                    self.checkpoint(done, row["wall_s"])
                    last_checkpoint = time.perf_counter()
                bar.update(1)
                bar.set_postfix(loss=f"{row['loss']:.4g}", dE00=f"{last_eval.get('dE00_mean', float('nan')):.2f}")
        except KeyboardInterrupt:
            bar.close()
            self.checkpoint(done, time.perf_counter() - t_start)
            raise RunInterrupted(f"interrupted at iteration {done} of {cfg.iterations}; the checkpoint is in "
                                 f"{self.folder}; continue with --resume (Python: resume=True)", self.folder,
                                 done) from None
        bar.close()
        ta_io.write_csv(os.path.join(self.folder, "log.csv"), self.rows, LOG_FIELDS)

    def log_estimate(self, done, step_s, over=1):
        """Log the seconds of iteration ``done`` (timed, not guessed) and what the rest of the job will take at
        that pace (:func:`job_estimate`): the iterations left, the evaluations left (each as long as the start's, or
        ``eval_spp / spp`` iterations when this call made none) and the results (quantised and rendered as the naive
        baseline was, or as two evaluations without one, and :data:`RESULTS_S` for the files and figures)."""
        cfg = self.cfg
        evaluation_s = self.evaluation_s if self.evaluation_s is not None else step_s * cfg.eval_spp / cfg.spp
        results_s = (self.quantised_s if self.quantised_s is not None else 2 * evaluation_s) + RESULTS_S
        total, parts = job_estimate(cfg.iterations, done, cfg.eval_every, step_s, evaluation_s, results_s)
        took = (f"iteration {done} took {step_s:.3g} s" if over == 1 else
                f"iterations {done - over + 1}-{done} took {step_s:.3g} s each")
        self.log(f"optimize_print: {took} at {cfg.spp} spp; the rest of the job about {duration_text(total)} "
                 f"({parts})")
        return step_s

    def finish(self):
        """Results: continuous, quantised, exports, figures, views; the summary."""
        cfg, target, inks, folder, rows = self.cfg, self.target, self.inks, self.folder, self.rows
        # the last iteration's evaluation is this render (same state, same seed); a run resumed after its last
        # iteration renders it again, before the (N, D, H, W) weights exist: the two are not held together
        done, renders = self.evaluated
        optimized = renders if done == cfg.iterations else self.evaluate()
        self.evaluated = (None, None)
        target.save_texels(folder, "optimized", optimized.mean(0), self.subset)
        weights = self.model.weights().detach().cpu()  # quantised, exported and drawn on the CPU
        indices, final_print, final_renders = self.quantized(weights, self.fixed)
        scores, texel_de = self.score(final_renders, texels=True)
        final = {"image": self.picture(final_print, final_renders).numpy(), **scores, "texel_dE00": texel_de}
        target.save_texels(folder, "final", final["image"])
        final.update(target.extra_scores(final_renders))
        # what quantisation costs: the quantised print's expected colours against the continuous optimum's (both
        # free of render noise; the halftone grain is in it)
        quantisation = self.score(final_renders, against=optimized)
        ta_io.atomic_write_bytes(os.path.join(folder, "mixture.npz"), npz_bytes(
            weights=np.asarray(weights.numpy(), np.float32), inks=np.array(inks.names), voxel_size_mm=cfg.voxel_size))
        save_index_volume(os.path.join(folder, "quantized.npz"), indices, inks, cfg.printer_dpi)
        export_slices(indices, inks, os.path.join(folder, "slices"), dpi=cfg.printer_dpi)
        write_figures(folder, rows, cfg, target, inks, weights, final, self.baseline, self.remap)
        view_seconds = target.views(folder, final_print, inks, cfg, self.eval_seed, texel_de, log=self.log,
                                    texel_index=self.subset)
        del final_print  # an object's prepared copy and micro-grid SDF (1.8 GB at 40 mm)
        package = None
        if cfg.printer is not None:  # the printer's package of the run's volume (pipelines.print.package)
            from .package import export_run
            package = export_run(folder, os.path.join(folder, f"package-{load_printer(cfg.printer).name}"),
                                 cfg.printer, force=True, progress=False, log=self.log)

        baseline, remap = self.baseline, self.remap
        opt_rows = [r for r in rows if r["iteration"] > 0]
        hidden = ("image", "texel_dE00")
        summary = {
            "kind": target.kind,
            "iterations": cfg.iterations,
            "wall_s": rows[-1]["wall_s"],
            "seconds_per_iteration": (rows[-1]["wall_s"] / max(1, len(opt_rows))) if opt_rows else None,
            **target.describe(), "spp": cfg.spp, "eval_spp": cfg.eval_spp,
            "evaluation": {"renders": EVAL_RENDERS, "spp_each": cfg.eval_spp // EVAL_RENDERS,
                           "texels": target.describe()["texels"] if self.subset is None else len(self.subset),
                           "seconds": self.eval_seconds, "picture_seconds": self.picture_seconds,
                           "share_of_job": self.eval_seconds / (time.perf_counter() - self.t_call),
                           "estimator": "torch_appearance.print_error.noise_free_error: CIEDE2000 extrapolated to "
                                        "infinitely many samples; *_raw: the mean of the renders scored as it is"},
            "final_quantized": {k: v for k, v in final.items() if k not in hidden},
            "optimized_continuous": self.score(optimized),
            "quantisation_vs_continuous": quantisation,
            "baseline_naive_extrusion": None if baseline is None else
            {k: v for k, v in baseline.items() if k not in hidden},
            "baseline_remap_25d": None if remap is None else {k: v for k, v in remap.items() if k not in hidden},
            "initial": {k: rows[0][k] for k in LOG_FIELDS if k in rows[0] and k.startswith("dE")},
            "loss_first_last": [rows[0].get("loss"), rows[-1].get("loss")],
            "quantized_shape_dhw": list(indices.shape), "printer_dpi": list(cfg.printer_dpi),
            "parameters": int(self.model.logits.numel()), "views_s": view_seconds, "halftone": cfg.halftone,
            "package": None if package is None else {"printer": package["printer"]["name"],
                                                     "seconds": package["seconds"]["total"]},
            # the whole call: preparation, baselines, iterations, evaluations, quantisation and outputs (a resumed
            # run: its own call only)
            "job_s": time.perf_counter() - self.t_call,
            "device": str(self.device),  # where the iterations ran (cfg.device; a resumed run: its last call's)
        }
        ta_io.write_json(os.path.join(folder, "summary.json"), summary)
        naive_text = "" if baseline is None else f", naive extrusion {_scores_text(baseline)}"
        remap_text = "" if remap is None else f", 2.5D remapped {_scores_text(remap)}"
        self.log(f"optimize_print: {cfg.iterations} iterations in {summary['wall_s']:.1f} s (the whole job "
                 f"{summary['job_s'] / 60:.1f} min); CIEDE2000 mean ± SE / p95 of the print, free of render noise: "
                 f"final (quantised) {_scores_text(final)}{naive_text}{remap_text}; the {cfg.eval_spp}-spp evaluation "
                 f"render alone would read {final['dE00_mean_raw']:.2f} (its noise {final['dE00_noise']:.2f}) "
                 f"-> {folder}")
        return summary
