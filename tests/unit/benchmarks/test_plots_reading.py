"""benchmarks.plots on a multirun folder: axes with units and direction, a failed job named under the figure,
no error-bar legend entry where no error bar is drawn, and pipeline-check jobs (trainer=smoke) marked."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib.pyplot as plt
import pytest
from matplotlib.container import ErrorbarContainer

from benchmarks.plots.sweep import FIGURES, PIPELINE_CHECK, draw_figure, figure_data, failed_note, main, read_sweeps

SIGMAS = (0.0, 0.01, 0.02)


def _job(folder: Path, sigma: float, trainer: str, error_r: float | None) -> None:
    """A src.train job of a noise sweep: its overrides, Hydra's choices, config and metrics (or a failure)."""
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text(f"- data.pair.noise_sigma={sigma}\n- trainer={trainer}\n")
    (folder / ".hydra" / "hydra.yaml").write_text(f"hydra:\n  runtime:\n    choices:\n      trainer: {trainer}\n")
    (folder / "config_resolved.yaml").write_text(
        "task_name: gaussian_noise\nsampling: ts\npartial: prnet\nvariant: null\nseed: 1\n"
        "data: {dataset: synthetic, splits: {train: {split: train, categories: half1}, test: {split: test, categories: half2}},"
        f" pair: {{noise_sigma: {sigma}, overlap_ratio: null}}}}\n"
        "model: {network: {_target_: src.models.omnet.OMNet, num_iters: 4, trans_loss_weight: 4.0}}\n")
    if error_r is None:
        (folder / "failure.json").write_text(json.dumps({"status": "failed", "reason": "ValueError: bad pair"}))
    else:
        (folder / "metrics.json").write_text(json.dumps({"metrics": {"Error(R)": error_r, "Error(t)": error_r / 100}}))


@pytest.fixture
def sweep(tmp_path) -> Path:
    """A smoke-trained noise sweep of 4 jobs, the last of which failed."""
    root = tmp_path / "multirun" / "noise"
    for i, sigma in enumerate(SIGMAS):
        _job(root / str(i), sigma, "smoke", 40.0 + i)
    _job(root / "3", 0.03, "smoke", None)
    return root


def test_a_sweeps_figure_states_units_failures_and_pipeline_checks(sweep):
    frame, failed = read_sweeps([sweep])
    assert list(failed["job"]) == ["3"]
    stats = figure_data(frame, FIGURES["noise"], None)
    fig = draw_figure(stats, FIGURES["noise"], failed_note(failed))
    axes = [ax for ax in fig.axes if ax.get_title()]
    assert [ax.get_ylabel() for ax in axes] == ["Error(R) (degrees), lower is better ↓",
                                                "Error(t) (shapes' units), lower is better ↓"]
    assert all("units" in ax.get_xlabel() for ax in axes)
    legend = axes[0].get_legend()
    labels = [text.get_text() for text in legend.get_texts()]
    assert labels[0] == f"OMNet [{PIPELINE_CHECK}]"
    assert not any(isinstance(c, ErrorbarContainer) for ax in axes for c in ax.containers)  # one run per point
    assert all(line.get_linestyle() == "--" for ax in axes for line in ax.get_lines())
    footnote = " ".join(text.get_text() for text in fig.texts)
    assert "1 job(s) absent from the curves" in footnote and "noise/3: failed (ValueError: bad pair)" in footnote
    assert "Points: one run each (no error bars)" in footnote and "not a result" in footnote
    plt.close(fig)


def test_error_bars_are_drawn_where_points_have_several_runs(sweep, tmp_path):
    for i, sigma in enumerate(SIGMAS):
        _job(sweep / f"{i}_again", sigma, "default", 30.0 + 2 * i)
        _job(sweep / f"{i}_third", sigma, "default", 34.0 + 2 * i)
    frame, _ = read_sweeps([sweep])
    fig = draw_figure(figure_data(frame, FIGURES["noise"], None), FIGURES["noise"])
    ax = fig.axes[0]
    kinds = {label: type(handle).__name__ for handle, label in zip(*ax.get_legend_handles_labels())}
    assert kinds == {f"OMNet [{PIPELINE_CHECK}]": "Line2D", "OMNet": "ErrorbarContainer"}
    plt.close(fig)


def test_the_command_writes_beside_the_sweep_and_prints_the_failed_job(sweep, capsys):
    assert main([str(sweep), "--figures", "noise", "--no-paper"]) == 0
    out = capsys.readouterr().out
    assert "note: 1 job(s) absent from the curves" in out
    assert (sweep / "error_vs_noise.png").is_file()
