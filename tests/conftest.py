import sys
from pathlib import Path

# Tests import their helpers (tiny_scene) and, across the package folders that mirror vq_mitsuba's,
# each other's (test_ui's requests) directly.
sys.path[:0] = [str(Path(__file__).parent)] + sorted(str(d) for d in Path(__file__).parent.iterdir()
                                                     if d.is_dir() and not d.name.startswith((".", "_")))


import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

# Every property-based test tries the same examples on every run (a seed from the test's own
# name), writes no example database into the checkout, and has no deadline on a loaded machine;
# tests/fuzzing.py sets the number of examples of each fuzz test.
settings.register_profile("vq-mitsuba", derandomize=True, database=None, deadline=None)
settings.load_profile("vq-mitsuba")


def pytest_runtest_setup(item):
    """Tests marked cpu_inputs build CPU tensors for the renderer: they run where the process's
    device is the CPU (every CI run), and are skipped on a GPU."""
    if item.get_closest_marker("cpu_inputs") is not None:
        from vq_mitsuba.backend import torch_device

        if torch_device().type != "cpu":
            pytest.skip("builds its inputs as CPU tensors; the process runs on a GPU")

# Short enough for the default suite; the discrete branch starts at vq.warmup_frac of these steps.
THREE_MATERIAL_SETTINGS = ["train.iterations=360", "train.batch_rays=768", "train.bounce_after=1000",
                           "train.checkpoint_every=1000"]


@pytest.fixture(scope="session")
def three_materials(tmp_path_factory):
    """(capture XML, RunDir) of the three-sphere capture fitted with the defaults (both branches)."""
    from tiny_scene import write_three_material_capture
    from vq_mitsuba.config import load_config
    from vq_mitsuba.run.run_dir import RunDir
    from vq_mitsuba.engine.pipeline import fit

    out = tmp_path_factory.mktemp("three")
    capture = write_three_material_capture(out)
    run = out / "run"
    fit(capture, run, load_config(None, THREE_MATERIAL_SETTINGS))
    return capture, RunDir(run)
