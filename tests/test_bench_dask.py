"""``granite bench`` on Dask: the smoke study (VO only on assets/sequences) gives the same
results.csv serially, on a LocalCluster of 2 worker processes, and on a real ``dask scheduler``
with ``dask worker`` subprocesses on 127.0.0.1, also when a worker is killed mid-study; a tiny
rendered study (64x48, 4 frames) renders in frame-range tasks and resumes.

results.csv is compared without its timing columns (``granite.bench.tasks.TIMING_COLUMNS``:
``vo_fps``, ``vo_wall_s``), the only ones that differ between two runs of the same study."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from granite.bench.execute import run_study
from granite.bench.report import read_results
from granite.bench.study import load_study
from granite.bench.tasks import TIMING_COLUMNS
from granite.cli.main import main

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "studies" / "assets_smoke.toml"
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}


@pytest.fixture(scope="module")
def serial_results(tmp_path_factory) -> list[dict]:
    out = tmp_path_factory.mktemp("serial")
    rows, failed = run_study(load_study(SMOKE), out)
    assert not failed and len(rows) == 4 and all(r["status"] == "ok" for r in rows)
    results = read_results(out / "results.csv", timing=False)
    assert results and not set(TIMING_COLUMNS) & set(results[0])
    assert all(float(r["rpe_fixed_scale_rmse"]) > 0 for r in results)  # the fixed-scale RPE of each run
    return results


def _check_outputs(out: Path) -> None:
    for name in ("results.csv", "report.md", "metrics.png", "trajectories/aggressive.png"):
        assert (out / name).is_file(), name
    for seq in ("aggressive", "default"):
        for variant in ("ours", "reference"):
            assert (out / "runs" / seq / variant / "trajectory.tum").is_file()
    report = (out / "report.md").read_text()
    assert "Table I: failures" in report and "Table II: RMS RPE" in report
    assert "alignment scale fixed (scale drift counts)" in report


def test_local_cluster_equals_serial(serial_results, tmp_path, capsys):
    out = tmp_path / "study"
    assert main(["bench", str(SMOKE), "--out", str(out), "--workers", "2",
                 "--dashboard-address", "127.0.0.1:0"]) == 0
    printed = capsys.readouterr().out
    assert "local cluster tcp://127.0.0.1:" in printed
    assert "2 worker processes on 127.0.0.1; dashboard http://127.0.0.1:" in printed
    assert "[9/9" in printed
    assert read_results(out / "results.csv", timing=False) == serial_results
    _check_outputs(out)
    # resumed: nothing left to run, the same table
    assert main(["bench", str(SMOKE), "--out", str(out), "--serial"]) == 0
    assert "0 tasks to run (finished and kept: 4 vo, 4 evaluate)" in capsys.readouterr().out
    assert read_results(out / "results.csv", timing=False) == serial_results


def test_local_cluster_listens_on_loopback_only():
    from granite.bench.execute import local_cluster

    with local_cluster(1, "127.0.0.1:0") as cluster:
        addresses = [cluster.scheduler_address, *(w.worker_address for w in cluster.workers.values())]
        assert all(a.startswith("tcp://127.0.0.1:") for a in addresses), addresses


def _start(args: list[str], **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", *args], cwd=ROOT, env=ENV, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, **kw)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


class Cluster:
    """``dask scheduler`` and ``dask worker`` subprocesses on 127.0.0.1 (random ports);
    ``tls``: the --tls-* options of all of them (the protocol is then tls)."""

    def __init__(self, folder: Path, workers: list[str], tls: list[str] | None = None):
        self.file = folder / "scheduler.json"
        tls = tls or []
        self.procs = [_start(["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
                              "--no-dashboard", "--scheduler-file", str(self.file), *tls,
                              *(["--protocol", "tls"] if tls else [])])]
        deadline = time.monotonic() + 60
        while not self.file.is_file() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert self.file.is_file(), "the scheduler did not start"
        time.sleep(0.3)
        self.address = json.loads(self.file.read_text())["address"]
        assert self.address.startswith(("tls" if tls else "tcp") + "://127.0.0.1:")
        self.workers = {}
        for name in workers:
            self.workers[name] = _start(["distributed.cli.dask_worker", self.address, "--name", name,
                                         "--nworkers", "1", "--nthreads", "1", "--host", "127.0.0.1",
                                         "--no-dashboard", *tls])
            self.procs.append(self.workers[name])
        from distributed import Client

        with Client(self.address, timeout="30s", security=self.security(tls)) as client:
            client.wait_for_workers(len(workers), timeout=60)

    @staticmethod
    def security(tls: list[str]):
        if not tls:
            return None
        from distributed.security import Security

        opts = dict(zip(tls[::2], tls[1::2]))
        return Security(tls_ca_file=opts["--tls-ca-file"], tls_client_cert=opts["--tls-cert"],
                        tls_client_key=opts["--tls-key"], require_encryption=True)

    def close(self) -> None:
        for proc in reversed(self.procs):
            _stop(proc)


@pytest.fixture()
def cluster_factory(tmp_path):
    made = []

    def make(workers, tls=None):
        made.append(Cluster(tmp_path, workers, tls))
        return made[-1]

    yield make
    for c in made:
        c.close()


def test_scheduler_and_worker_subprocesses(serial_results, cluster_factory, tmp_path, capsys):
    cluster = cluster_factory(["w0"])
    out = tmp_path / "study"
    assert main(["bench", str(SMOKE), "--out", str(out), "--scheduler", cluster.address]) == 0
    assert f"scheduler {cluster.address}: 1 workers" in capsys.readouterr().out
    assert read_results(out / "results.csv", timing=False) == serial_results
    _check_outputs(out)


def _certificates(folder: Path) -> list[str]:
    """A CA and one certificate signed by it (the docs/bench.md commands)."""
    def openssl(*args):
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)

    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=test CA",
            "-keyout", "ca.key", "-out", "ca.pem")
    openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=granite-bench", "-keyout", "node.key",
            "-out", "node.csr")
    openssl("x509", "-req", "-in", "node.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-days", "2", "-out", "node.pem")
    return ["--tls-ca-file", str(folder / "ca.pem"), "--tls-cert", str(folder / "node.pem"),
            "--tls-key", str(folder / "node.key")]


def test_tls_cluster(serial_results, cluster_factory, tmp_path, capsys):
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command")
    tls = _certificates(tmp_path)
    cluster = cluster_factory(["w0"], tls)
    out = tmp_path / "study"
    # without a client certificate the scheduler cannot be reached
    assert main(["bench", str(SMOKE), "--out", str(out), "--scheduler", cluster.address]) == 2
    assert "needs --tls-ca-file" in capsys.readouterr().err
    plain = cluster.address.replace("tls://", "tcp://")
    import dask

    with dask.config.set({"distributed.comm.timeouts.connect": "3s"}):
        assert main(["bench", str(SMOKE), "--out", str(out), "--scheduler", plain]) == 2
    assert "cannot connect to the scheduler" in capsys.readouterr().err
    assert main(["bench", str(SMOKE), "--out", str(out), "--scheduler", cluster.address, *tls]) == 0
    assert read_results(out / "results.csv", timing=False) == serial_results


def test_killed_worker_mid_study(serial_results, cluster_factory, tmp_path):
    from distributed import Client

    cluster = cluster_factory(["victim", "survivor"])
    out = tmp_path / "study"
    log = (tmp_path / "bench.log").open("w")
    bench = subprocess.Popen([sys.executable, "-m", "granite.cli.main", "bench", str(SMOKE), "--out", str(out),
                              "--scheduler", cluster.address], cwd=ROOT, env=ENV, stdout=log,
                             stderr=subprocess.STDOUT)
    killed = None
    try:
        with Client(cluster.address, timeout="30s") as client:
            deadline = time.monotonic() + 120
            while killed is None and time.monotonic() < deadline and bench.poll() is None:
                info = client.scheduler_info(n_workers=-1)["workers"]
                for address, keys in client.processing().items():
                    if info.get(address, {}).get("name") == "victim" and any(str(k).startswith("vo-") for k in keys):
                        time.sleep(0.5)  # inside the VO run
                        os.killpg(cluster.workers["victim"].pid, signal.SIGKILL)
                        killed = [str(k) for k in keys]
                        break
                time.sleep(0.1)
        assert killed, "no VO task ran on the victim worker"
        assert bench.wait(300) == 0, (tmp_path / "bench.log").read_text()
    finally:
        if bench.poll() is None:
            bench.kill()
        log.close()
    assert cluster.workers["victim"].wait(10) is not None
    assert read_results(out / "results.csv", timing=False) == serial_results
    _check_outputs(out)


@pytest.mark.blender
def test_tiny_rendered_study_renders_in_ranges_and_resumes(tmp_path, capsys):
    pytest.importorskip("bpy")
    study_file = tmp_path / "tiny.toml"
    study_file.write_text("""
name = "tiny"
seeds = [1]
frames_per_task = 2
[render]
width = 64
height = 48
samples = 1
[[scenario]]
scenario = "default"
frames = "0:4"
overrides = { terrain = { extent = 32.0, far_extent = 0.0, resolution = 1.0, crater_density = 0.0 } }
[[variant]]
name = "ours"
""")
    out = tmp_path / "out"
    assert main(["bench", str(study_file), "--out", str(out), "--serial"]) == 0
    printed = capsys.readouterr().out
    assert "5 tasks to run" in printed and "frames 0:2" in printed and "frames 2:4" in printed
    seq = out / "sequences" / "default_seed1_64x48_0-4"
    images = sorted((seq / "mav0" / "cam0" / "data").glob("*.png"))
    assert len(images) == 4
    assert "seed = 1" in (seq / "scenario.toml").read_text()
    assert (out / "runs" / seq.name / "ours" / "diagnostics.csv").is_file()
    rows = read_results(out / "results.csv")
    assert len(rows) == 1 and rows[0]["seed"] == "1" and rows[0]["images"] == "4"
    # a lost frame and its task: only that range is rendered again, bit-identically
    first = images[0].read_bytes()
    images[0].unlink()
    (seq / ".bench" / "render-0-2.done").unlink()
    (seq / ".bench" / "complete.json").unlink()
    assert main(["bench", str(study_file), "--out", str(out), "--serial"]) == 0
    printed = capsys.readouterr().out
    assert "frames 0:2" in printed and "frames 2:4" not in printed
    assert images[0].read_bytes() == first
    # the same study on 2 workers (ranges rendered concurrently into one folder): the same frames
    out2 = tmp_path / "out2"
    assert main(["bench", str(study_file), "--out", str(out2), "--workers", "2",
                 "--dashboard-address", "127.0.0.1:0"]) == 0
    seq2 = out2 / "sequences" / seq.name
    for name in ("mav0/cam0/data", "mav0/depth0/data"):
        files = sorted(p.name for p in (seq / name).iterdir())
        assert files == sorted(p.name for p in (seq2 / name).iterdir())
        assert all((seq / name / f).read_bytes() == (seq2 / name / f).read_bytes() for f in files)
    manifest = json.loads((seq2 / "manifest.json").read_text())
    assert all(f["render_seconds"] is not None for f in manifest["frames"][:4])
    assert read_results(out2 / "results.csv", timing=False) == read_results(out / "results.csv", timing=False)
    # a changed study does not overwrite the old render
    study_file.write_text(study_file.read_text().replace("samples = 1", "samples = 2"))
    assert main(["bench", str(study_file), "--out", str(out), "--serial"]) == 2
    assert "holds a render of a different scenario" in capsys.readouterr().err


def test_bench_vo_wrapper(tmp_path):
    """benchmarks/bench_vo.py keeps its options; it runs them as a study."""
    proc = subprocess.run([sys.executable, "benchmarks/bench_vo.py", "--datasets", "assets/sequences/aggressive",
                           "--config", "configs/reference.toml", "--data", str(tmp_path), "--serial"],
                          cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    # the row holds what a direct run of the VO with that configuration gives
    from granite.estimator.config import VoConfig
    from granite.estimator.runner import run_vo
    from granite.evaluation import evaluate
    from granite.io import open_dataset

    dataset = open_dataset(ROOT / "assets" / "sequences" / "aggressive")
    direct = run_vo(dataset, VoConfig.load(ROOT / "configs" / "reference.toml"), progress=False)
    ev = evaluate(direct.trajectory, dataset.ground_truth, delta=1.0)
    row = (f"| aggressive (all) | reference | {ev.restarts} | {ev.tracking_percentage:.1f} | "
           f"{ev.rpe.rmse:.3f} | {100 * ev.ate.rmse / ev.path_length:.2f} % |")
    assert row in proc.stdout, (row, proc.stdout)
    assert (tmp_path / "bench_vo.json").is_file() and (tmp_path / "report.md").is_file()
