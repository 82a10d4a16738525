"""The wood fit's figures: every title inside the canvas (issue 49 item 10: fit_vs_photo.png's titles were clipped)."""
import math

import numpy as np
import pytest

from torch_appearance.pipelines.wood import report


@pytest.mark.parametrize("shape", [(64, 64), (32, 128), (128, 40)])
def test_figure_titles_inside_canvas(tmp_path, monkeypatch, shape):
    saved = {}
    original = report.ta_io.save_figure

    def capture(fig, path, dpi=120):
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        canvas = FigureCanvasAgg(fig)
        canvas.draw()   # the layout engine runs at draw time, as when saving
        renderer = canvas.get_renderer()
        box = fig.bbox
        texts = [t for ax in fig.axes for t in (ax.title, ax.xaxis.label, ax.yaxis.label) if t.get_text()]
        saved[path.rsplit("/", 1)[-1]] = [(t.get_text(), t.get_window_extent(renderer)) for t in texts]
        assert all(e.x0 >= box.x0 - 0.5 and e.x1 <= box.x1 + 0.5 and e.y0 >= box.y0 - 0.5 and e.y1 <= box.y1 + 0.5
                   for _, e in saved[path.rsplit("/", 1)[-1]]), f"{path}: a title leaves the canvas"
        original(fig, path, dpi)

    monkeypatch.setattr(report.ta_io, "save_figure", capture)
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0, 1, shape + (3,)).astype(np.float32)
    err = rng.uniform(-math.pi, math.pi, shape)
    rows = ([{"stage": 1, "wall_s": 0.1 * i, "phase_loss": 1.0 / (i + 1)} for i in range(4)]
            + [{"stage": 2, "wall_s": 1 + 0.1 * i, "color_loss": 1.0 / (i + 1)} for i in range(4)])
    report.figures(str(tmp_path), rows, rgb, rgb, err)
    assert {"fit_vs_photo.png", "convergence.png"} <= set(saved)
    assert any("photo" == text for text, _ in saved["fit_vs_photo.png"])
    assert (tmp_path / "fit_vs_photo.png").stat().st_size > 0
