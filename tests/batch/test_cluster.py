"""`batch --address` on a Ray cluster of two nodes started on this machine with Ray's own test
helper (`ray.cluster_utils.Cluster`), each node with one CPU of its own: the runs land on both
nodes; when the second node is removed mid-batch, its run is retried on the head and resumes from
its checkpoint; no step is lost and summary.md says what happened."""

import csv
import threading
import time

import pytest

from tiny_scene import write_sphere_capture
from vq_mitsuba.batch import run_batch
from vq_mitsuba.run.run_dir import RunDir

ray = pytest.importorskip("ray")

# a fit of a few seconds (about 70 steps a second on one core), checkpointed often
SETTINGS = ["--set", "train.iterations=400", "--set", "train.checkpoint_every=5", "--set", "train.batch_rays=64",
            "--set", "vq.enabled=false", "--set", "residual.iterations=0"]


def _tries(out, run: str) -> list[str]:
    """The nodes of a run's tries, in order, from its log."""
    lines = (out / "logs" / f"{run}.log").read_text().splitlines()
    return [line.split(": try on ", 1)[1] for line in lines if line.startswith("# batch ") and ": try on " in line]


@pytest.mark.slow
def test_a_batch_on_a_two_node_cluster_loses_a_node_and_nothing_else(tmp_path):
    from ray.cluster_utils import Cluster

    captures = [str(write_sphere_capture(tmp_path / name, size=16, n_views=4, spp=8)) for name in ("a", "b")]
    out = tmp_path / "batch"
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        second = cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        head_id, second_id = cluster.head_node.node_id[:8], second.node_id[:8]
        removed = {}

        def remove_the_second_node_once_its_run_has_a_checkpoint():
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline and not removed:
                for run in ("a-s0", "b-s0"):
                    log = out / "logs" / f"{run}.log"
                    if (log.is_file() and any(n.endswith(second_id) for n in _tries(out, run))
                            and (out / run / RunDir.CHECKPOINT).is_file()):
                        removed["run"] = run
                        removed["step"] = RunDir(out / run).load_state()["step"]
                        cluster.remove_node(second)
                        break
                time.sleep(0.05)

        watcher = threading.Thread(target=remove_the_second_node_once_its_run_has_a_checkpoint)
        watcher.start()
        rows = run_batch(captures, out, seeds=[0], fit_args=SETTINGS, address=cluster.address)
        watcher.join()
    finally:
        cluster.shutdown()
    assert removed, "no run reached a checkpoint on the second node"
    lost, other = removed["run"], ({"a-s0", "b-s0"} - {removed["run"]}).pop()
    status = {r["run"]: r for r in rows}
    assert all(r["status"] == "done" for r in rows), rows
    # the runs landed on both nodes; the lost one was tried again on the head
    assert [n[-8:] for n in _tries(out, other)] == [head_id]
    assert [n[-8:] for n in _tries(out, lost)] == [second_id, head_id]
    assert status[lost]["tries"] == 2 and status[lost]["node"].endswith(head_id)
    # nothing lost: both runs have every step, and the retry went on from a checkpoint the second node wrote
    for run in ("a-s0", "b-s0"):
        assert RunDir(out / run).load_state()["step"] == 400 and RunDir(out / run).fit_summary()["iterations"] == 400
    fit = RunDir(out / lost).fit_summary()
    resumed_from = 400 - fit["steps_this_call"]
    assert removed["step"] <= resumed_from < 400
    assert f"resumed from its checkpoint at step {resumed_from}" in status[lost]["message"]
    with open(out / "summary.csv") as f:
        table = {r["run"]: r for r in csv.DictReader(f)}
    assert table[lost]["tries"] == "2" and table[other]["tries"] == "1"
    summary_md = (out / "summary.md").read_text()
    assert head_id in summary_md and second_id in summary_md and f"needed more than one try" in summary_md
    assert f"| {lost} | done: retried: 1 earlier try lost (on " in summary_md
