#!/usr/bin/env python
"""Wood appearance matching on real cube-face photos (Mokume samples), scored against U-Net ring maps (not a test).

For every face (``CN03`` / ``H11`` × ``A``..``F``: 256×256 photos of the six faces of two small wood cubes, MIT,
see DATA/README.txt) the wood fit (torch_appearance.pipelines.wood_fit.fit_wood) runs into ``OUT/<face>/``, and the
table reports: rings traced, phase RMS initial → final (rad), mean |wrapped phase error| (rad), SSIM of the fit vs
the photo, detection time (Gabor + tracing, s), board-estimate time (s), fit time (stage 1 + stage 2, s), the fitted
mean ring width (mm) and a boundary F-measure at ``--tolerance-px`` against the ``<L>_arl-unet.png`` map.

The arl map is the authors' U-Net prediction of annual-ring lines (bright = ring line), i.e. a WEAK label (model
output, not a human annotation). It is thresholded (Otsu), thinned to a one-pixel skeleton
(cv2.ximgproc.thinning) and compared with our ring boundaries: the iso-lines G = k + boundary_lateness of the fitted
model rendered at the photo's size (model_boundaries). Sensitivity = skeleton pixels within the tolerance of our
boundaries; precision = our boundary samples (1 px steps) within the tolerance of a skeleton pixel; F1 their
harmonic mean. The U-Net line follows the dark latewood band, our boundary the latewood → earlywood step, so a
systematic offset of a fraction of a ring width is expected even for a perfect fit.

Faces where no board geometry can be fitted (radial faces, end grain: fit_wood raises ValueError) get the status
"refused: <message>". The dataset does not give a pixel size: ``--pixel-size-mm 0.2`` (256 px ≈ 51 mm) is an
ASSUMPTION; it scales the reported ring widths (mm) and the depth of the fitted tree axis, not the 2D fit quality.

Outputs (atomic writes): ``OUT/faces.json`` (settings + one row per face), ``OUT/faces.md`` (the markdown table),
``OUT/faces.png`` (montage; columns = faces, rows = photo, fit, |phase error|, our boundaries in red + arl
skeleton in green over the photo) and one fit_wood run folder per face. ``--photometric`` runs the fit's stage 3
(geometry + colour map against the photo's colours through the reparameterised render) and adds a before/after
table (phase RMS vs the photo's phase, SSIM, latewood contrast = 5-95 % luminance spread of the fit / of the photo)
and a "fit before stage 3" row to the montage.

Examples:
    python scripts/eval/eval_wood_faces.py                                   # all 12 faces, default fit settings
    python scripts/eval/eval_wood_faces.py --faces CN03_A,H11_B --epochs 20 --color-epochs 5 --out /tmp/faces
    python scripts/eval/eval_wood_faces.py --data /path/to/wood_faces_mokume --pixel-size-mm 0.15
"""
import argparse
import math
import os
import sys
import time

import numpy as np

from torch_appearance import io as ta_io
from torch_appearance.cli.fit_wood import add_fit_arguments, config_from_args
from torch_appearance.rings.evaluation import boundary_f_measure

PROG = "eval_wood_faces.py"
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DEFAULT_DATA = os.path.normpath(os.path.join(REPO, "..", "shared", "data", "wood_faces_mokume"))
ALL_FACES = [f"{cube}_{L}" for cube in ("CN03", "H11") for L in "ABCDEF"]

FIELDS = [  # (key, header, format)
    ("face", "face", "{}"),
    ("status", "status", "{}"),
    ("rings_traced", "rings", "{}"),
    ("initial_phase_rms", "phase RMS init", "{:.3f}"),
    ("final_phase_rms", "phase RMS final", "{:.3f}"),
    ("mean_abs_wrapped_phase_error", "mean abs phase err", "{:.3f}"),
    ("ssim_fit_vs_photo", "SSIM", "{:.3f}"),
    ("mean_ring_width_mm", "ring width mm", "{:.2f}"),
    ("arl_sensitivity", "arl sens", "{:.2f}"),
    ("arl_precision", "arl prec", "{:.2f}"),
    ("arl_f1", "arl F1", "{:.2f}"),
    ("contrast_ratio", "contrast fit/photo", "{:.2f}"),
    ("detect_s", "detect s", "{:.1f}"),
    ("board_estimate_s", "board s", "{:.2f}"),
    ("fit_s", "fit s", "{:.1f}"),
]
CONTRAST_FIELDS = [  # with --contrast-match: the same face before and after the luminance remap of the colour map
    ("face", "face", "{}"),
    ("status", "status", "{}"),
    ("cm_ssim_before", "SSIM before", "{:.3f}"),
    ("cm_ssim_after", "SSIM after", "{:.3f}"),
    ("cm_contrast_before", "contrast before", "{:.2f}"),
    ("cm_contrast_after", "contrast after", "{:.2f}"),
    ("cm_rmse_before", "colour RMSE before", "{:.4f}"),
    ("cm_rmse_after", "colour RMSE after", "{:.4f}"),
]
PHOTOMETRIC_FIELDS = [  # with --photometric: the same face before and after stage 3
    ("face", "face", "{}"),
    ("status", "status", "{}"),
    ("phase_rms_before", "phase RMS before", "{:.3f}"),
    ("phase_rms_after", "phase RMS after", "{:.3f}"),
    ("ssim_before", "SSIM before", "{:.3f}"),
    ("ssim_after", "SSIM after", "{:.3f}"),
    ("contrast_before", "contrast before", "{:.2f}"),
    ("contrast_after", "contrast after", "{:.2f}"),
    ("stage3_s", "stage 3 s", "{:.1f}"),
]


# ------------------------------------------------------------------------------------------------------------
# weak labels and the boundary F-measure
# ------------------------------------------------------------------------------------------------------------
def arl_skeleton(arl):
    """``(M, 2)`` ``(x, y)`` pixels of the one-pixel skeleton of an arl map (uint8 (H, W), bright = ring line),
    and the binary mask it came from (Otsu threshold)."""
    import cv2

    a = np.asarray(arl)
    if a.ndim == 3:
        a = a[..., 0]
    a = a.astype(np.uint8)
    _, mask = cv2.threshold(a, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    skel = cv2.ximgproc.thinning(mask, thinningType=cv2.ximgproc.THINNING_ZHANGSUEN)
    ys, xs = np.nonzero(skel)
    return np.stack([xs, ys], 1).astype(np.float64), mask > 0


# ------------------------------------------------------------------------------------------------------------
# one face
# ------------------------------------------------------------------------------------------------------------
def face_paths(data, face):
    cube, letter = face.split("_")
    return os.path.join(data, cube, f"{letter}_col.png"), os.path.join(data, cube, f"{letter}_arl-unet.png")


def evaluate_face(data, face, out, args, log):
    """Fit one face and score it; returns (row, panels) where panels holds the montage images (or None)."""
    import torch
    from torch_appearance.nn.wood import WoodModel
    from torch_appearance.pipelines.wood import fit_wood, model_boundaries

    photo, arl_path = face_paths(data, face)
    arl = np.rint(ta_io.read_image(arl_path, space="srgb", name="arl map")[..., 0] * 255).astype(np.uint8)
    label, _ = arl_skeleton(arl)
    rgb = ta_io.read_png(photo)
    folder = os.path.join(out, face)
    row = {"face": face, "photo": os.path.abspath(photo), "run_folder": os.path.abspath(folder),
           "arl_label_pixels": int(len(label))}
    panels = {"photo": rgb, "label": label}
    cfg = config_from_args(args, photo=photo, out=folder, pixel_size_mm=args.pixel_size_mm, preview=False, seed=0)
    t0 = time.perf_counter()
    try:
        summary = fit_wood(cfg, progress=False, log=log)
    except ValueError as exc:
        row.update(status=f"refused: {exc}", wall_s=time.perf_counter() - t0)
        return row, panels
    wall = time.perf_counter() - t0
    h, w = summary["image_hw"]
    model = WoodModel.load(os.path.join(folder, "model"))
    with torch.no_grad():
        G = model.render_board(h, w, args.pixel_size_mm)["G"].numpy()
    lines = model_boundaries(G, summary["boundary_lateness"])
    fm = boundary_f_measure(lines, label, args.tolerance_px)
    t = summary["timings_s"]
    row.update(
        status="ok" if summary["fit_ok"] else "poor fit",
        rings_traced=summary["rings_traced"], initial_phase_rms=summary["initial_phase_rms"],
        final_phase_rms=summary["final_phase_rms"],
        mean_abs_wrapped_phase_error=summary["mean_abs_wrapped_phase_error"],
        ssim_fit_vs_photo=summary["ssim_fit_vs_photo"], mean_ring_width_mm=summary["mean_ring_width_mm"],
        ring_scale_mm=summary["ring_scale_mm"], boundary_lateness=summary["boundary_lateness"],
        boundaries=len(lines), arl_sensitivity=fm["sensitivity"], arl_precision=fm["precision"], arl_f1=fm["f1"],
        arl_mean_error_px=fm["mean_error_px"], detect_s=t["gabor_s"] + t["tracing_s"],
        board_estimate_s=t["board_estimate_s"], fit_s=t["stage1_s"] + t["stage2_s"], wall_s=wall,
        fit_ok=summary["fit_ok"], contrast_ratio=summary["latewood_contrast"]["ratio"])
    cm = summary.get("contrast_match")
    if cm is not None:
        row.update(cm_ssim_before=cm["before"]["ssim"], cm_ssim_after=cm["after"]["ssim"],
                   cm_contrast_before=cm["before"]["latewood_contrast"]["ratio"],
                   cm_contrast_after=cm["after"]["latewood_contrast"]["ratio"],
                   cm_rmse_before=cm["before"]["colour_rmse"], cm_rmse_after=cm["after"]["colour_rmse"])
    ph = summary.get("photometric")
    if ph is not None:
        row.update(phase_rms_before=ph["before"]["phase_rms"], phase_rms_after=ph["after"]["phase_rms"],
                   ssim_before=ph["before"]["ssim"], ssim_after=ph["after"]["ssim"],
                   contrast_before=ph["before"]["latewood_contrast"]["ratio"],
                   contrast_after=ph["after"]["latewood_contrast"]["ratio"], stage3_s=ph["seconds"])
        row["fit_s"] += ph["seconds"]
        panels["fit_before"] = ta_io.read_png(os.path.join(folder, "fit_before_photometric.png"))
    phase = np.load(os.path.join(folder, "phase.npy"))
    fit_phase = np.load(os.path.join(folder, "fit_phase.npy"))
    panels.update(fit=ta_io.read_png(os.path.join(folder, "fit.png")),
                  err=np.abs(np.angle(np.exp(1j * (phase - fit_phase)))), lines=lines)
    return row, panels


# ------------------------------------------------------------------------------------------------------------
# output
# ------------------------------------------------------------------------------------------------------------
def montage(rows, panels, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(rows)
    before = any("fit_before" in p for p in panels)
    k = 5 if before else 4
    fig, axes = plt.subplots(k, n, figsize=(2.3 * n + 0.6, 2.4 * k), squeeze=False)
    titles = ["photo"] + (["fit before stage 3", "fit after stage 3"] if before else ["fit"]) + [
        "|phase error| (0..π)", "ours (red) vs arl (green)"]
    o = 1 if before else 0
    for j, (row, p) in enumerate(zip(rows, panels)):
        srgb = np.clip(p["photo"], 0, 1) ** (1 / 2.2)
        axes[0, j].imshow(srgb)
        axes[0, j].set_title(row["face"], fontsize=9)
        if "fit" in p:
            if before:
                axes[1, j].imshow(np.clip(p["fit_before"], 0, 1) ** (1 / 2.2))
                axes[1, j].set_title(f"SSIM {row['ssim_before']:.2f}, φ RMS {row['phase_rms_before']:.2f}", fontsize=8)
                axes[2, j].set_title(f"SSIM {row['ssim_after']:.2f}, φ RMS {row['phase_rms_after']:.2f}", fontsize=8)
            axes[1 + o, j].imshow(np.clip(p["fit"], 0, 1) ** (1 / 2.2))
            axes[2 + o, j].imshow(p["err"], cmap="magma", vmin=0, vmax=math.pi)
            axes[2 + o, j].set_title(f"mean {row['mean_abs_wrapped_phase_error']:.2f} rad", fontsize=8)
            axes[3 + o, j].set_title(f"F1 {row['arl_f1']:.2f}", fontsize=8)
        else:
            for i in range(1, 3 + o):
                axes[i, j].text(0.5, 0.5, "refused", ha="center", va="center", transform=axes[i, j].transAxes)
        axes[3 + o, j].imshow(srgb * 0.7)
        lab = p["label"]
        axes[3 + o, j].plot(lab[:, 0], lab[:, 1], ",", color="lime")
        for line in p.get("lines", []):
            axes[3 + o, j].plot(line[:, 0], line[:, 1], "-", color="red", lw=0.7)
        h, w = srgb.shape[:2]
        for i in range(k):
            axes[i, j].set(xlim=(-0.5, w - 0.5), ylim=(h - 0.5, -0.5))
            axes[i, j].set_xticks([])
            axes[i, j].set_yticks([])
            if j == 0:
                axes[i, j].set_ylabel(titles[i], fontsize=9)
    fig.tight_layout()
    ta_io.save_figure(fig, path, dpi=100)


def parse_faces(text):
    faces = [f.strip() for f in text.split(",") if f.strip()]
    bad = [f for f in faces if f not in ALL_FACES]
    if bad or not faces:
        raise ValueError(f"--faces: unknown face(s) {', '.join(bad) or '(none)'}; expected a comma list of "
                         f"{', '.join(ALL_FACES)}")
    return list(dict.fromkeys(faces))


def main(argv=None):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default=DEFAULT_DATA, help="folder holding CN03/ and H11/ (default: "
                                                        "../shared/data/wood_faces_mokume next to the checkout)")
    p.add_argument("--faces", default=",".join(ALL_FACES), help="comma list of faces <cube>_<letter> "
                                                                "(default: all 12)")
    p.add_argument("--pixel-size-mm", type=float, default=0.2,
                   help="pixel pitch in mm; an ASSUMPTION, the dataset does not give it (default: %(default)s)")
    p.add_argument("--tolerance-px", type=float, default=3.0, help="boundary F-measure tolerance in px "
                                                                   "(default: %(default)s)")
    # the fit's own flags (with --contrast-match / --photometric: each face reported before and after)
    add_fit_arguments(p, ["epochs", "color_epochs", "contrast_match", "photometric", "photometric_estimator"])
    p.add_argument("--out", default="results/wood_faces", help="output folder (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        faces = parse_faces(args.faces)
    except ValueError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    if not (math.isfinite(args.pixel_size_mm) and args.pixel_size_mm > 0):
        print(f"{PROG}: error: --pixel-size-mm must be > 0; got {args.pixel_size_mm}", file=sys.stderr)
        return 2
    if args.epochs < 0 or args.color_epochs < 0:
        print(f"{PROG}: error: --epochs and --color-epochs must be >= 0", file=sys.stderr)
        return 2
    if not (math.isfinite(args.tolerance_px) and args.tolerance_px > 0):
        print(f"{PROG}: error: --tolerance-px must be > 0; got {args.tolerance_px}", file=sys.stderr)
        return 2
    if not os.path.isdir(args.data):
        print(f"{PROG}: error: --data: {args.data!r} is not a folder (expected the Mokume sample faces "
              f"CN03/ and H11/ with <L>_col.png and <L>_arl-unet.png)", file=sys.stderr)
        return 2
    missing = [f for face in faces for f in face_paths(args.data, face) if not os.path.isfile(f)]
    if missing:
        print(f"{PROG}: error: data missing under {args.data!r}: {', '.join(missing)}", file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)

    from torch_appearance.progress import progress_bar
    rows, panels = [], []
    bar = progress_bar(faces, desc="faces", unit="face")
    for face in bar:
        row, pan = evaluate_face(args.data, face, args.out, args, log=bar.write)
        rows.append(ta_io.nan_to_none(row))
        panels.append(pan)

    table = ta_io.markdown_table(rows, FIELDS)
    if args.contrast_match:
        table += "\n\nContrast match, before → after:\n\n" + ta_io.markdown_table(rows, CONTRAST_FIELDS)
    if args.photometric:
        table += "\n\nStage 3 (photometric), before → after:\n\n" + ta_io.markdown_table(rows, PHOTOMETRIC_FIELDS)
    settings = (f"pixel size {args.pixel_size_mm:g} mm (assumed), epochs {args.epochs} + colour "
                f"{args.color_epochs}, F-measure tolerance {args.tolerance_px:g} px vs Otsu-thresholded, thinned "
                f"arl-unet map (weak label)")
    print(table)
    print(settings)
    ta_io.write_json(os.path.join(args.out, "faces.json"),
                     {"data": os.path.abspath(args.data), "pixel_size_mm": args.pixel_size_mm,
                      "pixel_size_assumed": True, "epochs": args.epochs, "color_epochs": args.color_epochs,
                      "tolerance_px": args.tolerance_px, "photometric": args.photometric,
                      "contrast_match": args.contrast_match,
                      "photometric_estimator": args.photometric_estimator,
                      "label": "arl-unet (U-Net output, Otsu + thinning)",
                      "faces": rows})
    ta_io.atomic_write_bytes(os.path.join(args.out, "faces.md"),
                             f"# Wood fit on Mokume cube faces\n\n{settings}\n\n{table}\n".encode())
    montage(rows, panels, os.path.join(args.out, "faces.png"))
    print(f"-> {os.path.join(args.out, 'faces.json')}, faces.md, faces.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
