"""The optimiser's columns of ``diagnostics.csv``: ``gn_iterations`` (every Gauss-Newton / LM
iteration spent on a frame, the pose refinement's included) and ``gn_converged`` (whether the frame's main optimisation stopped
by its step rule rather than at ``max_iterations``). Checked against the solver's own reports,
recorded per frame by wrapping :meth:`SlidingWindow.optimize` and
:meth:`SlidingWindow.refine_pose`, and against the stopping rule's
two extremes."""

from __future__ import annotations

from pathlib import Path

import pytest

from granite.backend.window import SlidingWindow
from granite.estimator.config import VoConfig
from granite.estimator.diagnostics import FrameDiagnostics, diagnostics_to_csv, read_diagnostics
from granite.estimator.vo import MonocularVO
from granite.io import open_dataset

ASSET = Path(__file__).resolve().parents[1] / "assets" / "sequences" / "default"
FRAMES = 40


def _run(monkeypatch, backend: dict | None = None):
    """(diagnostics, reports) of the first FRAMES frames; ``reports[i]``: the (kwargs, report)
    of every ``optimize`` and ``refine_pose`` (the re-optimisation after outlier removal) call
    made while frame i was processed."""
    reports: dict[int, list] = {}
    current = {"frame": None}

    def recording(method):
        def record(self, *args, **kwargs):
            report = method(self, *args, **kwargs)
            reports.setdefault(current["frame"], []).append((kwargs, report))
            return report
        return record

    monkeypatch.setattr(SlidingWindow, "optimize", recording(SlidingWindow.optimize))
    monkeypatch.setattr(SlidingWindow, "refine_pose", recording(SlidingWindow.refine_pose))
    ds = open_dataset(ASSET)
    vo = MonocularVO(ds.calibration.camera(), VoConfig.from_dict({"backend": backend or {}}))
    diags = []
    for i, frame in enumerate(ds.frames(0, FRAMES)):
        current["frame"] = i
        diags.append(vo.process(i, frame.timestamp, frame.image).diagnostics)
    return diags, reports


def test_columns_sum_the_frames_optimisations(monkeypatch):
    diags, reports = _run(monkeypatch)
    tracked = [d for d in diags if d.state == "tracking"]
    assert len(tracked) > FRAMES // 2
    with_extra = 0
    for d in diags:
        calls = reports.get(d.frame_index, [])
        assert d.gn_iterations == sum(r.iterations for _, r in calls)
        main = [r for kw, r in calls if "snapshot_iteration" in kw]
        assert len(main) <= 1
        assert d.gn_converged == (main[0].converged if main else None)
        with_extra += len(calls) > 1
    assert with_extra > 0  # keyframes' extra iterations are counted too
    assert any(d.gn_iterations > 0 and d.gn_converged for d in tracked)


def test_converged_follows_the_step_rule(monkeypatch):
    never, _ = _run(monkeypatch, {"step_tolerance": 0.0, "max_iterations": 3})
    main_ran = [d for d in never if d.gn_converged is not None]
    assert main_ran and not any(d.gn_converged for d in main_ran)
    assert all(d.gn_iterations >= 3 for d in main_ran if d.state == "tracking")
    always, _ = _run(monkeypatch, {"step_tolerance": 1e3})
    main_ran = [d for d in always if d.gn_converged is not None]
    assert main_ran and all(d.gn_converged for d in main_ran)


def test_columns_round_trip_with_empty_convergence(tmp_path):
    rows = [FrameDiagnostics(0.0, 0, 0, "init"),
            FrameDiagnostics(0.05, 1, 0, "tracking", gn_iterations=9, gn_converged=False),
            FrameDiagnostics(0.10, 2, 0, "tracking", gn_iterations=3, gn_converged=True)]
    path = tmp_path / "diagnostics.csv"
    path.write_text(diagnostics_to_csv(rows))
    back = read_diagnostics(path)
    assert [(r.gn_iterations, r.gn_converged) for r in back] == [(0, None), (9, False), (3, True)]
    lines = path.read_text().splitlines()
    at = lines[0].split(",").index("gn_converged")
    assert [line.split(",")[at] for line in lines[1:]] == ["", "0", "1"]


def test_a_file_without_the_columns_reads_with_their_defaults(tmp_path):
    text = diagnostics_to_csv([FrameDiagnostics(0.0, 0, 0, "tracking", gn_iterations=4)])
    header, row = text.splitlines()
    keep = [i for i, c in enumerate(header.split(",")) if not c.startswith("gn_")]
    path = tmp_path / "old.csv"
    path.write_text("\n".join(",".join(line.split(",")[i] for i in keep)
                              for line in (header, row)) + "\n")
    (back,) = read_diagnostics(path)
    assert back.gn_iterations == 0 and back.gn_converged is None


def test_scale_drift_reason_is_written_only_where_the_indicator_is_empty(tmp_path):
    from granite.backend import ScaleDriftResult
    from granite.backend.scale_drift import NO_SCALE_LINK
    from granite.estimator.vo import _set_scale_drift

    rows = [FrameDiagnostics(0.0, 0, 0, "tracking"), FrameDiagnostics(0.05, 1, 0, "tracking"),
            FrameDiagnostics(0.10, 2, 0, "lost")]
    _set_scale_drift(rows[0], ScaleDriftResult(None, None, 5, 1e-9, 1e5, 0.3, NO_SCALE_LINK))
    _set_scale_drift(rows[1], ScaleDriftResult(0.02, 0.01, 5, 3.0, 1e5, 0.3, ""))
    _set_scale_drift(rows[2], None)
    path = tmp_path / "diagnostics.csv"
    path.write_text(diagnostics_to_csv(rows))
    back = read_diagnostics(path)
    assert [r.scale_drift_reason for r in back] == [NO_SCALE_LINK, "", ""]
    assert back[0].scale_drift_indicator is None and back[1].scale_drift_indicator == 0.02


def test_run_summary_and_report_count_the_optimiser_and_the_scale(tmp_path):
    """``summary.json``'s optimiser and Λ counts against counts made here, and the report's
    lines that state them (the no-scale line only when there is such a frame)."""
    from granite.backend.scale_drift import NO_SCALE_ANCHOR, NO_SCALE_LINK
    from granite.estimator.runner import optimization_summary
    from granite.visualization.report import Report, report_markdown

    rows = [FrameDiagnostics(0.0, 0, 0, "init"),
            FrameDiagnostics(0.05, 1, 0, "tracking", gn_iterations=3, gn_converged=True,
                             scale_drift_reason="fewer than 3 keyframes"),
            FrameDiagnostics(0.10, 2, 0, "tracking", gn_iterations=9, gn_converged=False,
                             scale_drift_reason=NO_SCALE_LINK),
            FrameDiagnostics(0.15, 3, 0, "tracking", gn_iterations=4, gn_converged=True,
                             scale_drift_indicator=0.02),
            FrameDiagnostics(0.20, 4, 0, "tracking", gn_iterations=7, gn_converged=False,
                             scale_drift_reason=NO_SCALE_ANCHOR)]
    out = optimization_summary(rows)
    assert out == {"gn_mean_iterations": (3 + 9 + 4 + 7) / 4, "gn_unconverged_frames": 2,
                   "gn_optimized_frames": 4, "scale_drift_defined_frames": 1,
                   "scale_drift_no_scale_frames": 2}
    summary = {"frames": 5, "estimated_frames": 5, "skipped_frames": 0, "restarts": 0,
               "submaps": 1, "keyframes": 2, "mean_processing_ms": 10.0, **out}
    text = report_markdown("t", [], summary, None, None, Report())
    assert "- Gauss-Newton: 5.8 iterations per frame" in text and "converging on 2 of 4 frames" in text
    assert "Λ_scaledrift defined on 1 frames; **no scale information on 2 frames**" in text
    quiet = report_markdown("t", [], {**summary, **optimization_summary(rows[:2] + rows[3:4])}, None, None, Report())
    assert "no scale information" not in quiet and "Λ_scaledrift defined on 1 frames" in quiet
