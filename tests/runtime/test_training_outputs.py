"""Training outputs: the metrics CSV (crash-safe, resumable), wandb offline, plots, GIFs."""

from __future__ import annotations

import csv
import json
import math
import sys
import warnings

import numpy as np
import pytest

from pe_rlhf.runtime.metrics_logger import MetricsLogger, flatten_eval_summary, read_metrics_csv
from pe_rlhf.runtime.plots import TESTING_PANEL, plot_learning_curves
from pe_rlhf.runtime.video import CAPTION_HEIGHT


def _read(path):
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        return reader.fieldnames, list(reader)


# -- CSV -----------------------------------------------------------------------------------------


def test_csv_rows_and_new_columns_readable_while_open(tmp_path):
    path = tmp_path / "metrics.csv"
    with MetricsLogger(tmp_path) as logger:
        logger.log(100, {"train/takeover_rate": 0.5, "loss/qvalue": 1.25})
        header, rows = _read(path)  # read while the logger still holds the file
        assert header == ["step", "train/takeover_rate", "loss/qvalue"]
        assert rows == [{"step": "100", "train/takeover_rate": "0.5", "loss/qvalue": "1.25"}]

        logger.log(200, {"train/takeover_rate": np.float32(0.25), "eval/success_rate_mean": 1})
        header, rows = _read(path)
        assert header == ["step", "train/takeover_rate", "loss/qvalue", "eval/success_rate_mean"]
        assert [r["step"] for r in rows] == ["100", "200"]
        assert rows[0]["eval/success_rate_mean"] == "" and rows[1]["loss/qvalue"] == ""
        assert rows[1]["eval/success_rate_mean"] == "1"

        logger.log(300, {"loss/qvalue": 0.75})
        _, rows = _read(path)
        assert len(rows) == 3 and rows[2]["loss/qvalue"] == "0.75"
        assert logger.last_step == 300
    assert not list(tmp_path.glob(".metrics*"))  # no temporary files left behind
    columns, parsed = read_metrics_csv(path)
    assert columns[0] == "step" and parsed[1] == {"step": 200.0, "train/takeover_rate": 0.25,
                                                  "eval/success_rate_mean": 1.0}


def test_declare_and_bad_values(tmp_path):
    with MetricsLogger(tmp_path) as logger:
        logger.declare(["a", "b"])
        assert _read(tmp_path / "metrics.csv")[0] == ["step", "a", "b"]
        with pytest.raises(TypeError, match="'a'"):
            logger.log(1, {"a": "text"})
        with pytest.raises(ValueError, match="reserved"):
            logger.log(1, {"step": 3})
    with pytest.raises(RuntimeError, match="closed"):
        logger.log(2, {"a": 1.0})
    logger.close()  # idempotent


def test_non_finite_values_blank_and_warned_once(tmp_path):
    with MetricsLogger(tmp_path) as logger:
        with pytest.warns(RuntimeWarning, match="'loss/actor'"):
            logger.log(1, {"loss/actor": float("nan"), "loss/alpha": 0.1})
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the second NaN of the same key is silent
            logger.log(2, {"loss/actor": float("inf"), "loss/alpha": 0.2})
        with pytest.warns(RuntimeWarning, match="'loss/alpha'"):
            logger.log(3, {"loss/actor": 1.0, "loss/alpha": -math.inf})
    _, rows = _read(tmp_path / "metrics.csv")
    assert [r["loss/actor"] for r in rows] == ["", "", "1.0"]
    assert [r["loss/alpha"] for r in rows] == ["0.1", "0.2", ""]


def test_resume_drops_rows_from_the_resume_step(tmp_path):
    with MetricsLogger(tmp_path) as logger:
        for step in (100, 200, 300, 400):
            logger.log(step, {"train/takeover_rate": step / 1000})
        logger.log(300, {"eval/episodic_return_mean": 5.0})
    # the checkpoint was saved at step 300: rows at 300 and later are replayed by the resumed run
    with MetricsLogger(tmp_path, resume=True) as logger:
        assert logger.columns == ["step", "train/takeover_rate", "eval/episodic_return_mean"]
        assert logger.truncate_after(300) == 3
        assert logger.last_step == 200
        _, rows = _read(tmp_path / "metrics.csv")
        assert [r["step"] for r in rows] == ["100", "200"]
        logger.log(300, {"train/takeover_rate": 0.9})
    _, rows = _read(tmp_path / "metrics.csv")
    assert [r["step"] for r in rows] == ["100", "200", "300"]
    assert rows[-1]["train/takeover_rate"] == "0.9"
    # without resume the old file is replaced
    with MetricsLogger(tmp_path) as logger:
        logger.log(1, {"x": 1.0})
    assert [r["step"] for r in _read(tmp_path / "metrics.csv")[1]] == ["1"]


def test_flatten_eval_summary():
    summary = {"episodic_return": {"mean": 3.0, "std": 1.0}, "episodes": 5, "seeds": [1, 2],
               "failure_breakdown": {"timeout": 1}}
    assert flatten_eval_summary(summary) == {"eval/episodic_return_mean": 3.0,
                                             "eval/episodic_return_std": 1.0}


# -- wandb / TensorBoard -------------------------------------------------------------------------


def test_wandb_offline_run_directory(tmp_path, monkeypatch):
    try:
        import wandb  # noqa: F401
    except Exception as err:  # noqa: BLE001
        pytest.skip(f"wandb cannot be imported: {err}")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_API_KEY", "")  # no credentials, and a closed local port as the server
    monkeypatch.setenv("WANDB_BASE_URL", "http://127.0.0.1:9")
    with MetricsLogger(tmp_path, backends=["csv", "wandb"], config={"lr": 1e-4}) as logger:
        with pytest.warns(RuntimeWarning, match="loss/qvalue"):
            logger.log(1, {"train/takeover_rate": 0.5, "loss/qvalue": float("nan")})
        logger.log(2, {"train/takeover_rate": 0.25})
        assert logger.wandb_run is not None and logger.wandb_run.offline
    runs = list((tmp_path / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and list(runs[0].glob("run-*.wandb"))
    assert (tmp_path / "wandb_run_id").read_text().strip() == runs[0].name.rsplit("-", 1)[-1]
    assert len(_read(tmp_path / "metrics.csv")[1]) == 2


def test_tensorboard_missing_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # as if tensorboard were not installed
    with pytest.raises(ImportError, match="pip install tensorboard"):
        MetricsLogger(tmp_path / "tb", backends=["csv", "tensorboard"])
    assert not (tmp_path / "tb" / "metrics.csv").exists()  # failed before touching anything


# -- plots ---------------------------------------------------------------------------------------


def _synthetic_csv(out_dir, with_losses=True, with_std=True):
    rng = np.random.default_rng(0)
    with MetricsLogger(out_dir) as logger:
        total = 0.0
        for i, step in enumerate(range(500, 10_001, 500)):
            total += rng.poisson(0.5)
            row = {"train/safety_violations_total": total, "train/takeover_rate": 0.5 * 0.9**i,
                   "train/takeover_data_usage": 0.3 + 0.1 * 0.9**i, "train/value_takeover_rate": 0.2,
                   "train/intervention_cost": rng.uniform(0, 1)}
            if with_losses:
                row.update({"loss/qvalue": 10 * 0.8**i, "loss/actor": -5 + i * 0.1, "loss/alpha": -0.01})
            logger.log(step, row)
            if step % 2000 == 0:
                ev = {f"eval/{m}_mean": rng.uniform(0, 1) * (i + 1) for m, _ in TESTING_PANEL}
                ev["eval/success_rate_mean"] = i / 20
                if with_std:
                    ev.update({f"eval/{m}_std": 0.1 * ev[f"eval/{m}_mean"] for m, _ in TESTING_PANEL})
                logger.log(step, ev)
    return out_dir / "metrics.csv"


def test_plots_written_with_baseline(tmp_path):
    csv_path = _synthetic_csv(tmp_path)
    baseline = {"policy": "idm-mobil", "episodic_return": {"mean": 2.0, "std": 0.5},
                "success_rate": {"mean": 0.3, "std": 0.4}}
    json_path = tmp_path / "idm.json"
    json_path.write_text(json.dumps(baseline))
    for b in (baseline, json_path):
        written = plot_learning_curves(csv_path, tmp_path / "plots", baseline=b)
        assert set(written) == {"training", "testing"}
        for path in written.values():
            assert path.exists() and path.stat().st_size > 5_000
    assert not list((tmp_path / "plots").glob(".*"))


def test_plots_with_missing_columns(tmp_path):
    csv_path = tmp_path / "metrics.csv"
    with MetricsLogger(tmp_path) as logger:
        logger.log(100, {"train/takeover_rate": 0.5})
        logger.log(200, {"train/takeover_rate": 0.4, "eval/success_rate_mean": 0.5})  # no _std
        with pytest.warns(RuntimeWarning):
            logger.log(300, {"eval/success_rate_mean": float("nan")})
    written = plot_learning_curves(csv_path, tmp_path / "p")
    assert set(written) == {"training", "testing"}
    assert all(p.stat().st_size > 5_000 for p in written.values())
    # only training columns: no testing panel
    only_train = tmp_path / "t"
    with MetricsLogger(only_train) as logger:
        logger.log(1, {"loss/qvalue": 1.0})
    assert set(plot_learning_curves(only_train / "metrics.csv", only_train)) == {"training"}


def test_training_panel_marks_the_end_of_warmup(tmp_path):
    import matplotlib.pyplot as plt

    from pe_rlhf.runtime.plots import WARMUP_LABEL, _training_figure

    with MetricsLogger(tmp_path) as logger:
        for step in (50, 100, 150, 200):
            logger.log(step, {"train/takeover_rate": 1.0 if step <= 100 else 0.3, "loss/qvalue": 1.0})
    columns, rows = read_metrics_csv(tmp_path / "metrics.csv")
    fig, axes = _training_figure(rows, columns, warmup_steps=100)
    drawn = [ax for ax in axes.flat if ax.lines]  # (b) takeover rate and (f) losses
    assert len(drawn) == 2
    for ax in drawn:
        (line,) = [ln for ln in ax.lines if ln.get_label() == WARMUP_LABEL]
        assert list(line.get_xdata()) == [100.0, 100.0] and line.get_linestyle() == "--"
    assert WARMUP_LABEL in [t.get_text() for t in drawn[0].get_legend().get_texts()]
    plt.close(fig)
    fig, axes = _training_figure(rows, columns)  # warm-up length unknown: no line
    assert not any(ln.get_label() == WARMUP_LABEL for ax in axes.flat for ln in ax.lines)
    plt.close(fig)
    assert set(plot_learning_curves(tmp_path / "metrics.csv", tmp_path / "p", warmup_steps=100)) == {"training"}


# -- video ---------------------------------------------------------------------------------------


def test_episode_gif_idm_mobil(tmp_path):
    from PIL import Image

    from pe_rlhf.evaluation import make_policy
    from pe_rlhf.runtime.video import record_episode_gif

    path = tmp_path / "gifs" / "idm.gif"
    info = record_episode_gif(make_policy("idm-mobil", 0), None, 1000, path, max_steps=20)
    assert path.exists() and info["path"] == str(path)
    assert 1 <= info["steps"] <= 20 and info["frames"] == info["steps"] + 1
    assert info["scene_seed"] == 1000 and "success" in info
    assert info["drivers"] == {"agent": info["steps"]}
    with Image.open(path) as gif:
        assert gif.n_frames > 1
        assert gif.size == (600, 338 + CAPTION_HEIGHT)  # the 800x450 render at scale 0.75, captioned below


def test_episode_gif_captions_who_drives_in_a_takeover_run(tmp_path):
    """Filmed through the InterventionWrapper with a random agent, the professional takes over:
    the caption names the mentor (or physics) on those frames, in its colour, and the agent on the rest."""
    from PIL import Image

    from pe_rlhf.evaluation import make_policy
    from pe_rlhf.mentors import make_mentor
    from pe_rlhf.physics import IDMMobilPolicy
    from pe_rlhf.physics.safety import SafetyForecastValue
    from pe_rlhf.runtime.video import DRIVER_COLOURS, driver_of, label_frame, record_episode_gif
    from pe_rlhf.transforms import HybridActionSelector
    from pe_rlhf.wrappers import InterventionWrapper

    assert driver_of({}) == "agent" and driver_of({"is_intervention": True}) == "mentor"
    assert driver_of({"is_intervention": True, "physics_action": 0, "mentor_selected": False}) == "physics"
    frame = label_frame(np.zeros((40, 200, 3), np.uint8), "step   3    54 km/h", "mentor")
    assert frame.shape == (40 + CAPTION_HEIGHT, 200, 3) and not frame[:40].any()
    band = frame[40:].reshape(-1, 3)
    assert (band == DRIVER_COLOURS["mentor"]).all(axis=1).any()  # the driver's colour swatch
    assert (band == DRIVER_COLOURS["mentor"]).all(axis=1).mean() < 0.2

    path = tmp_path / "takeover.gif"
    info = record_episode_gif(make_policy("random", 0), None, 1000, path, max_steps=60,
                              wrap=lambda env: InterventionWrapper(
                                  env, make_mentor("professional", seed=0), physics=IDMMobilPolicy(),
                                  selector=HybridActionSelector(SafetyForecastValue(), epsilon_select=-0.5)),
                              keep_video=True)
    drivers = info["drivers"]
    assert sum(drivers.values()) == info["steps"] and drivers.get("mentor", 0) > 0 and drivers.get("agent", 0) > 0
    video = info["video"]
    swatch = {d: (video[:, -CAPTION_HEIGHT:].reshape(len(video), -1, 3) == c).all(axis=2).any(axis=1)
              for d, c in DRIVER_COLOURS.items()}
    for driver in DRIVER_COLOURS:  # each frame's swatch names its step's driver (the reset frame: agent)
        assert swatch[driver].sum() == drivers.get(driver, 0) + (driver == "agent")
    with Image.open(path) as gif:
        assert gif.size == (600, 338 + CAPTION_HEIGHT)
