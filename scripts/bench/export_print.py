"""Export time and peak memory of printer packages (issue 27): Spot at several sizes, for several printers.

For each size a run folder of Spot is made without optimising (the optimiser's own steps: voxelisation, the naive
extrusion as the mixture, quantisation at 600 × 300 × 940 DPI with the object's outside void, the files of a run
folder; the target texels stand in for the rendered print's colours of the 3MF), cached under --work. Each export then
runs in a child process (``ta-export-print``'s function), whose peak resident memory is read from the operating
system and compared with a child that only imports the package. Prints a Markdown table and writes
``export_print.json``.

Examples:
    python scripts/bench/export_print.py --sizes 20 40 --printers j750 j750-hq
    python scripts/bench/export_print.py --run results/spot --printers j750 --formats gcvf
"""
import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
SPOT = os.path.join(ROOT, "tests", "data", "meshes", "spot")


def make_spot_run(folder, height_mm, log=print):
    """A finished-looking run folder of Spot at ``height_mm`` (see the module docstring)."""
    import dataclasses

    import numpy as np
    import torch

    from torch_appearance import io as ta_io
    from torch_appearance.fabrication.export import save_index_volume
    from torch_appearance.pipelines.print import PrintConfig
    from torch_appearance.pipelines.print.baselines import quantize
    from torch_appearance.pipelines.print.config import iteration_seed, load_inks
    from torch_appearance.pipelines.print.loop import build_target
    from torch_appearance.pipelines.print.run_folder import npz_bytes

    cfg = PrintConfig(mesh=os.path.join(SPOT, "spot_triangulated.obj"), texture=os.path.join(SPOT, "spot_texture.png"),
                      height_mm=float(height_mm), out=folder).resolved()
    os.makedirs(folder, exist_ok=True)
    t0 = time.perf_counter()
    inks = load_inks(cfg.inks)
    target = build_target(cfg, log=log)
    target.use(inks, cfg)
    log(f"  voxelised {target.shape} in {time.perf_counter() - t0:.0f} s")
    weights, _ = target.naive_weights(inks, cfg)
    log(f"  naive extrusion after {time.perf_counter() - t0:.0f} s")
    indices = quantize(target, weights, inks, cfg, iteration_seed(cfg.seed, -2))
    log(f"  quantised {indices.shape} after {time.perf_counter() - t0:.0f} s")
    ta_io.write_json(os.path.join(folder, "config.json"), {
        **dataclasses.asdict(cfg), "inks": [dataclasses.asdict(i) for i in inks], "voxel_size_mm": cfg.voxel_size,
        "kind": target.kind, "torch": torch.__version__, "synthetic": "bench/export_print.py: no optimisation"})
    target.save_inputs(folder)
    np.save(os.path.join(folder, "final.npy"), target.target.numpy().astype(np.float32))
    ta_io.atomic_write_bytes(os.path.join(folder, "mixture.npz"), npz_bytes(
        weights=np.asarray(weights.numpy(), np.float32), inks=np.array(inks.names), voxel_size_mm=cfg.voxel_size))
    del weights
    save_index_volume(os.path.join(folder, "quantized.npz"), indices, inks, cfg.printer_dpi)
    log(f"  run folder written after {time.perf_counter() - t0:.0f} s")


def child(code):
    """Run ``code`` in a fresh interpreter; returns (seconds, that interpreter's own peak RSS in MB, Linux)."""
    t0 = time.perf_counter()
    # VmHWM: the peak of this process image (ru_maxrss would carry over the parent's peak from the fork)
    report = ("\nprint('PEAK_KB', [l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')][0])")
    out = subprocess.run([sys.executable, "-c", code + report], check=True, capture_output=True, text=True).stdout
    peak = [int(line.split()[1]) for line in out.splitlines() if line.startswith("PEAK_KB")][0]
    return time.perf_counter() - t0, peak / 1024


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=float, nargs="*", default=[20.0, 40.0], help="Spot heights in mm")
    p.add_argument("--run", nargs="*", default=[], help="existing run folders to export as well")
    p.add_argument("--printers", nargs="+", default=["j750", "j750-hq"])
    p.add_argument("--formats", default="gcvf,3mf,slices")
    p.add_argument("--work", default="results/bench_export")
    args = p.parse_args(argv)
    os.makedirs(args.work, exist_ok=True)
    runs = list(args.run)
    for size in args.sizes:
        folder = os.path.join(args.work, f"spot{size:g}mm")
        if not os.path.isfile(os.path.join(folder, "quantized.npz")):
            print(f"making the run folder of Spot at {size:g} mm")
            make_spot_run(folder, size)
        runs.append(folder)
    _, base = child("import torch_appearance.pipelines.print.package, torch_appearance.fabrication.threemf")
    rows = []
    for run in runs:
        for printer in args.printers:
            out = os.path.join(args.work, "packages", f"{os.path.basename(run.rstrip('/'))}-{printer}")
            code = ("from torch_appearance.pipelines.print.package import export_run; "
                    f"export_run({run!r}, {out!r}, {printer!r}, {args.formats!r}, force=True, progress=False)")
            seconds, peak = child(code)
            record = json.load(open(os.path.join(out, "export.json")))
            rows.append({"run": os.path.basename(run.rstrip("/")), "printer": printer, "volume": record["volume"],
                         "layers": record["shape_zyx"][0], "layer_px": f"{record['shape_zyx'][2]}x{record['shape_zyx'][1]}",
                         **{f"{k}_s": v for k, v in record["seconds"].items()}, "process_s": round(seconds, 1),
                         "peak_MB": round(peak), "peak_over_import_MB": round(peak - base),
                         **{f"{k}_MB": round(v["bytes"] / 2 ** 20, 1) for k, v in record["files"].items()
                            if "bytes" in v}})
            print(rows[-1], flush=True)
    fields = list(dict.fromkeys(k for r in rows for k in r))
    print(f"\nimport-only child: {base:.0f} MB\n")
    print("| " + " | ".join(fields) + " |\n|" + "---|" * len(fields))
    for r in rows:
        print("| " + " | ".join(str(r.get(k, "")) for k in fields) + " |")
    with open(os.path.join(args.work, "export_print.json"), "w") as handle:
        json.dump({"import_MB": base, "rows": rows}, handle, indent=2)


if __name__ == "__main__":
    main()
