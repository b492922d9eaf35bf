"""Bakes on a real Dask cluster (scheduler + worker processes): the local bake's lattice to
the bit, also after a worker is killed mid-bake, with checkpoints and resume."""

import logging
import os
import shutil
import signal
import threading

import numpy as np
import pytest

from isolume.baking import BakeConfig, BakeError, Lattice, bake
from isolume.baking.bake import Baker
from isolume.volumes.synthetic import make

distributed = pytest.importorskip("distributed")
cluster_module = pytest.importorskip("isolume.baking.cluster")


@pytest.fixture(scope="module")
def cluster():
    """Two single-threaded worker processes (restarted by their nannies when killed)."""
    with cluster_module.local_cluster(2, silence_logs=logging.CRITICAL) as local:
        yield local


def _same_bits(a: Lattice, b: Lattice) -> None:
    for name in ("values", "samples", "second", "facing"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.meta["stats"]["paths"] == b.meta["stats"]["paths"]
    assert a.meta["rays_traced"] == b.meta["rays_traced"]


@pytest.mark.parametrize("mode, env", [("irradiance", "sky:sun=3"), ("sh", "constant:1,1,1")])
def test_cluster_bake_equals_the_local_bake(cluster, mode, env):
    """Irradiance under the sky (chunks traced in one compiled call) and SH transfer (the
    vertex-by-vertex tracer): the same lattice from two worker processes as from threads."""
    config = BakeConfig(samples=16, bounces=2, env=env, mode=mode, sh_order=3)
    vol = make("engine", 32)
    local = bake(vol, config, workers=2)
    remote = bake(vol, config, scheduler=cluster.scheduler_address)
    assert np.count_nonzero(local.samples) > 5000
    _same_bits(local, remote)
    moved = remote.meta["cluster"]
    assert moved["tasks"] >= len(local.meta["plan"]["levels"]) - 1
    # a level scene is built once per worker that traces it, not once per task
    assert moved["scene_builds"] <= 2 * len(local.meta["plan"]["levels"])


class _KillingBar:
    """A progress bar that SIGKILLs a worker process busy with a task at its first update."""

    def __init__(self, client) -> None:
        self.client, self.killed, self.in_flight = client, None, 0
        self.pids = client.run(os.getpid)

    def update(self, _paths: int) -> None:
        if self.killed is None:
            busy = {w: keys for w, keys in self.client.processing().items() if keys}
            worker = sorted(busy)[0]
            self.in_flight = len(busy[worker])
            os.kill(self.pids[worker], signal.SIGKILL)
            self.killed = worker

    def set_postfix_str(self, *_args, **_kwargs) -> None:
        pass


@pytest.mark.slow
def test_a_worker_killed_mid_bake_costs_only_its_tasks(cluster, monkeypatch):
    """SIGKILL of a worker with tasks in flight: Dask runs them again, the master counts
    every task's result once, and the lattice is the local one to the bit."""
    monkeypatch.setattr(cluster_module, "PATHS_PER_TASK", 4096)  # many small tasks
    config = BakeConfig(samples=24, bounces=2, env="sky:sun=3")
    vol = make("engine", 32)
    local = bake(vol, config, workers=2)
    with distributed.Client(cluster) as client:
        baker = Baker(vol, config, backend=cluster_module.ClusterBackend(client=client))
        bar = _KillingBar(client)
        try:
            baker.run(bar=bar)
        finally:
            baker.close()
    assert bar.killed is not None and bar.in_flight > 0
    _same_bits(local, baker.lattice)
    assert baker.backend.traffic.tasks > 20


def test_interrupted_cluster_bake_keeps_whole_texels_and_resumes(cluster, tmp_path,
                                                                  monkeypatch):
    """Ctrl-C during a cluster bake saves the committed texels (whole passes only); the
    cluster resumes the file to the lattice a local resume of the same file gives."""
    monkeypatch.setattr(cluster_module, "PATHS_PER_TASK", 4096)
    config = BakeConfig(samples=12, bounces=1, env="constant:1,1,1")
    vol = make("engine", 32)  # 8 levels
    apply = cluster_module.ClusterBackend._apply
    calls = {"n": 0}

    def interrupting(self, *args):
        apply(self, *args)
        calls["n"] += 1
        if calls["n"] == 3:  # Ctrl-C with later levels in flight
            raise KeyboardInterrupt

    cluster_module.fingerprint()  # of the code as it is: the patch below stands for a
    # Ctrl-C, not for other code, and the master's fingerprint is made once per process
    monkeypatch.setattr(cluster_module.ClusterBackend, "_apply", interrupting)
    cut = tmp_path / "cut.npz"
    with pytest.raises(KeyboardInterrupt):
        bake(vol, config, out=cut, scheduler=cluster.scheduler_address)
    monkeypatch.setattr(cluster_module.ClusterBackend, "_apply", apply)
    saved = Lattice.load(cut, vol)
    finished = saved.samples > 0
    assert 0 < finished.sum() < saved.active.sum()
    assert (saved.samples[finished] == 12).all()
    copy = tmp_path / "copy.npz"
    shutil.copy(cut, copy)
    remote = bake(vol, config, out=cut, scheduler=cluster.scheduler_address)
    local = bake(vol, config, out=copy, workers=2)
    for name in ("values", "samples", "second", "facing"):
        np.testing.assert_array_equal(getattr(local, name), getattr(remote, name))
    np.testing.assert_array_equal(Lattice.load(cut, vol).values, remote.values)


def test_a_worker_with_other_code_is_refused(cluster, monkeypatch):
    """Workers check the master's fingerprint (isolume's sources, library versions)."""
    other = dict(cluster_module.fingerprint(), numba="0.0.1")
    monkeypatch.setattr(cluster_module, "fingerprint", lambda: other)
    with pytest.raises(BakeError, match=r"numba .* here, 0\.0\.1 on the master"):
        bake(make("sphere", 20), BakeConfig(samples=2, bounces=0),
             scheduler=cluster.scheduler_address)


def test_cli_bake_on_a_local_cluster(tmp_path, capsys):
    """``isolume bake --scheduler local:1``: the file of a local bake, and what moved."""
    from isolume.app.cli import main

    args = ["bake", "synthetic:sphere:24", "--samples", "4", "--bounces", "1"]
    assert main([*args, "--out", str(tmp_path / "c.npz"), "--scheduler", "local:1"]) == 0
    assert "cluster: " in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "l.npz"), "--workers", "1"]) == 0
    remote, local = Lattice.load(tmp_path / "c.npz"), Lattice.load(tmp_path / "l.npz")
    np.testing.assert_array_equal(remote.values, local.values)


@pytest.mark.parametrize("address, match", [
    ("local:0", "N ≥ 1"), ("local:two", "N ≥ 1"), ("tcp://host with space", "address"),
    ("tcp://127.0.0.1:9", "no Dask scheduler answered"),
])
def test_bad_scheduler_is_one_line(address, match):
    with pytest.raises(BakeError, match=match) as caught:
        cluster_module.connect(address, timeout=2)
    assert "\n" not in str(caught.value)


def test_task_groups_cover_the_level_and_follow_the_path_budget():
    rng = np.random.default_rng(3)
    texels = np.sort(rng.choice(100_000, 5000, replace=False))
    expected = rng.integers(0, 60, len(texels)).astype(float)
    groups = cluster_module.task_groups(texels, expected, paths_per_task=4096)
    bounds = np.array(groups)
    assert bounds[0, 0] == 0 and bounds[-1, 1] == len(texels)
    np.testing.assert_array_equal(bounds[1:, 0], bounds[:-1, 1])  # contiguous, disjoint
    sizes = np.array([expected[lo:hi].sum() for lo, hi in groups])
    # every group but the last ends on the first texel past a multiple of the budget
    assert (sizes[:-1] <= 4096 + expected.max()).all()
    assert len(groups) == pytest.approx(expected.sum() / 4096, abs=1.5)
    assert cluster_module.task_groups(texels[:0], expected[:0]) == []


def test_concurrent_tasks_build_a_level_scene_once(monkeypatch):
    """Two threads of one worker wanting the same level: one scene build."""
    builds = []

    def slow_scene(volume, iso, config):
        builds.append(iso)
        threading.Event().wait(0.2)
        return object()

    monkeypatch.setattr(cluster_module, "level_scene", slow_scene)
    monkeypatch.setattr(cluster_module.kernels, "warm_up", lambda: None)
    job = cluster_module._Job("t", cluster_module.fingerprint(), make("sphere", 8),
                              BakeConfig(), None, np.array([0.3, 0.5]), None, None,
                              np.uint32(0), np.ones(3), None)
    state = cluster_module._WorkerBake(job)
    got = []
    threads = [threading.Thread(target=lambda: got.append(state.scene(1))) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert builds == [0.5]
    assert got[0][0] is got[1][0] and sorted(s > 0 for _, s in got) == [False, True]


def test_a_cluster_without_workers_is_one_line(monkeypatch):
    monkeypatch.setattr(cluster_module, "CONNECT_TIMEOUT_S", 1.0)
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None,
                                  silence_logs=logging.CRITICAL) as empty, \
            distributed.Client(empty) as client:
        with pytest.raises(BakeError, match="no worker joined within 1 s"):
            Baker(make("sphere", 12), BakeConfig(samples=2),
                  backend=cluster_module.ClusterBackend(client=client))


def test_fingerprint_is_the_loaded_code_and_the_same_in_every_process():
    """Processes with other string hashing agree; other code or constants differ."""
    import subprocess
    import sys
    import types

    code = "from isolume.baking.cluster import fingerprint; print(fingerprint())"
    seen = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           env={**os.environ, "PYTHONHASHSEED": seed},
                           check=True).stdout for seed in ("1", "2")}
    assert seen == {f"{cluster_module.fingerprint()}\n"}

    def digest(source: str) -> str:
        module = types.ModuleType("probe")
        exec(compile(source, "probe.py", "exec"), module.__dict__)
        h = cluster_module.hashlib.sha256()
        cluster_module._digest_module(module, h)
        return h.hexdigest()

    base = "STEP = 0.5\ndef f(x):\n    return x * 2.0 + len({'a', 'b'})\n"
    assert digest(base) == digest(base)
    assert digest(base) != digest(base.replace("2.0", "2.5"))
    assert digest(base) != digest(base.replace("0.5", "0.25"))


def test_target_error_refinement_on_the_cluster_equals_the_local_one(cluster):
    """`--target-error` passes (a subset of texels, per-texel targets) on the cluster."""
    config = BakeConfig(samples=8, bounces=1, env="sky:sun=3", target_error=0.05,
                        max_samples=64)
    vol = make("torus", 24)
    local = bake(vol, config, workers=2)
    remote = bake(vol, config, scheduler=cluster.scheduler_address)
    assert local.samples.max() > 8  # some texels were refined
    _same_bits(local, remote)


def test_a_texel_error_bake_on_the_cluster_equals_the_local_one(cluster):
    """`--texel-error` passes (the nodes, then the fine bricks' texels) on the cluster."""
    config = BakeConfig(samples=8, bounces=1, env="sky:sun=3", texel_error=0.05)
    vol = make("torus", 32)
    local = bake(vol, config, workers=2)
    remote = bake(vol, config, scheduler=cluster.scheduler_address)
    assert local.meta["filled"]["filled"] > 0
    _same_bits(local, remote)
    assert local.meta["filled"] == remote.meta["filled"]


def test_a_task_dask_cancels_is_queued_again(cluster, monkeypatch):
    """A worker lost in flight can take a task's inputs with it: Dask cancels the task.
    The backend queues it once more (a new key) and the lattice is the local one to the
    bit; a task cancelled at every try stops the bake with the cluster's error."""
    config = BakeConfig(samples=4, bounces=1, env="constant:1,1,1")
    vol = make("engine", 24)
    local = bake(vol, config, workers=2)
    cluster_module.fingerprint()  # of the code as it is, before the patch below
    submit = cluster_module.ClusterBackend._submit_task
    cancelled = []

    def cancelling(self, task, owner, stream, every=False):
        submit(self, task, owner, stream)
        if every or not cancelled:
            future = next(f for f, t in owner.items() if t is task)
            self.client.cancel([future])
            cancelled.append(future.key)

    monkeypatch.setattr(cluster_module.ClusterBackend, "_submit_task", cancelling)
    with distributed.Client(cluster) as client:
        baker = Baker(vol, config, backend=cluster_module.ClusterBackend(client=client))
        try:
            baker.run()
        finally:
            baker.close()
    assert len(cancelled) == 1
    _same_bits(local, baker.lattice)
    monkeypatch.setattr(cluster_module.ClusterBackend, "_submit_task",
                        lambda self, task, owner, stream: cancelling(self, task, owner,
                                                                     stream, every=True))
    with distributed.Client(cluster) as client:
        baker = Baker(vol, config, backend=cluster_module.ClusterBackend(client=client))
        with pytest.raises(BakeError, match="failed on the cluster"):
            try:
                baker.run()
            finally:
                baker.close()
