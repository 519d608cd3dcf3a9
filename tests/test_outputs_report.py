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
