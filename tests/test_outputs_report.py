"""The run report: says which rasterizer path a run switched to, and when."""
from recgs_addon.core.outputs.report import write_run_report


def _metrics(compile_info):
    hist = [{"iteration": i, "psnr": 20.0 + i / 1000, "elapsed": i / 10, "gaussians": 1000 + i} for i in (250, 500)]
    return {"config": {"mode": "3dgs"}, "reason": "iteration limit", "iterations": 500, "history": hist,
            "compile": compile_info}


def test_report_names_the_path_the_run_switched_to(tmp_path):
    text = write_run_report(tmp_path / "a", _metrics({"switched_at": 276, "numba": "ready"})).read_text()
    assert "numba's kernels from step 276" in text
    text = write_run_report(tmp_path / "b", _metrics({"switched_at": 90, "numba": None})).read_text()
    assert "the compiled path from step 90" in text
    text = write_run_report(tmp_path / "c", _metrics({"switched_at": None})).read_text()
    assert "from step" not in text


def test_report_says_what_significance_pruning_removed(tmp_path):
    m = _metrics({"switched_at": None})
    m["view_support"] = {"median_views": 7.0, "share_le2": 0.1, "share_none": 0.01, "histogram": [1] * 11}
    m["config"]["density"] = {"name": "adc", "prune_weight": 0.25}
    m["density"] = {"cloned": 10, "needless": 31137}
    text = write_run_report(tmp_path / "a", m).read_text()
    assert "Median 7 training views carry a Gaussian" in text
    assert "removed 31,137 Gaussians that no view needed (under 0.25 pixel" in text
    m["density"]["needless"] = 0
    assert "no view needed" not in write_run_report(tmp_path / "b", m).read_text()
