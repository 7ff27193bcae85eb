"""
Sweeps against a Ray cluster: an address where none answers, and a real cluster started with ``ray start --head``
(token authentication on, as ``ray start`` has it by default): a driver without the token is refused with one
line, a driver with it runs a tiny sweep, and a SIGTERM to that driver stops its trial at a checkpoint that the
same command resumes. ``-m "not ray_cluster"`` leaves the cluster's tests out.
"""

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from sb3_collapse.commands.sweep import main
from sb3_collapse.errors import ClusterUnreachable
from sb3_collapse.runfolder import run_status
from sb3_collapse.sweep.cluster import check_cluster

# A trial that checkpoints: 60 agent steps of cartpole at action repeat 20, a checkpoint every 10 agent steps.
TRIAL = [
    "--tasks", "cartpole-balance", "--seeds", "1", "--variants", "drqv2", "--frames", "1200", "--action-repeat", "20",
    "--size", "36", "--hidden-dim", "32", "--feature-dim", "8", "--batch-size", "8", "--seed-frames", "400",
    "--eval-every-frames", "1200", "--eval-episodes", "1", "--checkpoint-every-frames", "200",
    "--collapse-metrics-every-frames", "0", "--replay-sampling", "sb3", "--cpus-per-trial", "1", "--no-progress-bar",
]  # fmt: skip


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_unreachable_cluster_is_one_line_exit_1_and_writes_nothing(tmp_path, capsys):
    pytest.importorskip("ray", reason="the sweep extra is not installed: pip install -e '.[sweep]'")
    address = f"127.0.0.1:{free_port()}"  # nothing listens there
    start = time.monotonic()
    with pytest.raises(ClusterUnreachable, match=rf"address {address}: no Ray cluster answered within 1 s"):
        check_cluster(address, timeout_s=1)
    assert time.monotonic() - start < 5
    out = tmp_path / "sweep"
    status = main([*TRIAL, "--out", str(out), "--address", address, "--connect-timeout", "1"])
    assert status == 1 and not out.exists()  # nothing written before the cluster answers
    assert capsys.readouterr().err.strip().splitlines() == [
        (
            f"error: --address {address}: no Ray cluster answered within 1 s (Connection refused). Start it (ray "
            "start --head, docs/sweeps.md) or correct the address, then run the same command again; nothing was "
            "written."
        )
    ]
    assert time.monotonic() - start < 20


@pytest.fixture(scope="module")
def ray_cluster():
    """A Ray cluster started with ``ray start --head --block`` (2 CPUs, its own ports and temporary folder), with
    token authentication and a token of its own; ends with the module. Yields its address and the environment of a
    driver that has the token."""
    pytest.importorskip("ray", reason="the sweep extra is not installed: pip install -e '.[sweep]'")
    import psutil

    temp_dir = Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))  # short: Ray's socket paths have a length limit
    port = free_port()
    token = secrets.token_hex(32)
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token, "OMP_NUM_THREADS": "1"}
    ports = {
        "--port": port, "--ray-client-server-port": free_port(), "--dashboard-agent-listen-port": free_port(),
        "--dashboard-agent-grpc-port": free_port(), "--metrics-export-port": free_port(),
        "--runtime-env-agent-port": free_port(), "--node-manager-port": free_port(),
        "--object-manager-port": free_port(),
    }  # fmt: skip
    command = [
        str(Path(sys.executable).with_name("ray")), "start", "--head", "--block", "--num-cpus", "2",
        "--temp-dir", str(temp_dir), "--include-dashboard", "false", "--disable-usage-stats",
        *(str(item) for flag_value in ports.items() for item in flag_value),
    ]  # fmt: skip
    log = temp_dir / "ray_start.log"
    with log.open("w") as output:
        head = subprocess.Popen(command, env=env, stdout=output, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while "Ray runtime started" not in log.read_text():
            assert head.poll() is None and time.monotonic() < deadline, log.read_text()[-2000:]
            time.sleep(0.2)
        yield {"address": f"127.0.0.1:{port}", "env": env, "temp_dir": temp_dir}
    finally:
        processes = [head, *psutil.Process(head.pid).children(recursive=True)] if head.poll() is None else []
        head.terminate()  # `ray start --block` ends the processes it started
        try:
            head.wait(timeout=20)
        except subprocess.TimeoutExpired:
            pass
        for process in processes:  # those that outlived it: this test's own processes only
            try:
                psutil.Process(process.pid).kill()
            except psutil.Error:
                pass
        shutil.rmtree(temp_dir, ignore_errors=True)


@pytest.mark.ray_cluster
def test_cluster_that_wants_a_token_is_one_line_and_exit_2(ray_cluster, tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("RAY_AUTH_TOKEN", raising=False)  # this process has no token of this cluster
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    out = tmp_path / "sweep"
    with pytest.raises(SystemExit) as exit_info:
        main([*TRIAL, "--out", str(out), "--address", ray_cluster["address"]])
    assert exit_info.value.code == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "Traceback" not in err and "gcs_client" not in err  # Ray's own log lines kept off the terminal
    (line,) = [line for line in err.splitlines() if "error:" in line]
    assert line.startswith(f"python -m sb3_collapse.sweep: error: --address {ray_cluster['address']}: the Ray cluster ")
    assert "wants an authentication token" in line and "set RAY_AUTH_MODE=token and the cluster's token" in line
    assert "RAY_AUTH_MODE=disabled" in line


def newest_checkpoint(folder):
    from sb3_collapse.run.checkpoints import checkpoint_folders

    kept = checkpoint_folders(folder / "checkpoints")
    return (kept[0], json.loads((kept[0] / "checkpoint.json").read_text())) if kept else (None, None)


@pytest.mark.ray_cluster
def test_sigterm_to_a_sweep_on_a_ray_start_cluster_stops_at_a_checkpoint_and_the_rerun_resumes(ray_cluster, tmp_path):
    out = tmp_path / "sweep"
    folder = out / "cartpole-balance" / "drqv2" / "seed_0"
    argv = [sys.executable, "-m", "sb3_collapse.sweep", *TRIAL, "--out", str(out), "--address", ray_cluster["address"]]
    driver = subprocess.Popen(argv, env=ray_cluster["env"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    output = {}
    reader = threading.Thread(target=lambda: output.update(zip(("out", "err"), driver.communicate())), daemon=True)
    reader.start()
    deadline = time.monotonic() + 240
    while newest_checkpoint(folder)[0] is None:  # the trial trains on the cluster and wrote a periodic checkpoint
        assert driver.poll() is None and time.monotonic() < deadline, output
        time.sleep(0.02)
    periodic_step, signal_time = newest_checkpoint(folder)[1]["agent_steps"], time.time()
    driver.send_signal(signal.SIGTERM)
    reader.join(timeout=120)
    assert driver.returncode == 75, output
    assert "Traceback" not in output["err"] + output["out"]
    lines = [line for line in output["out"].splitlines() if "pid=" not in line]
    assert "0 failed, 1 stopped at a checkpoint." in lines[-2]
    assert lines[-1] == "Stopped by SIGTERM: run the same command again to resume (exit status 75)."
    stopped, info = newest_checkpoint(folder)
    assert info["agent_steps"] > periodic_step and info["frames"] < 1200  # the checkpoint written at the signal
    assert (stopped / "checkpoint.json").stat().st_mtime >= signal_time
    assert run_status(folder) == "unfinished" and not (out / ".stop_requested").exists()
    assert json.loads((out / "sweep.json").read_text())["resources"]["address"] == ray_cluster["address"]

    rerun = subprocess.run(argv, check=False, env=ray_cluster["env"], capture_output=True, text=True, timeout=240)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert "1 finished now (1 resumed from a checkpoint)" in rerun.stdout
    assert f"from its checkpoint at frame {info['frames']:,} ({stopped.name})" in rerun.stdout
    result = json.loads((folder / "result.json").read_text())
    assert result["resumes"] == 1 and result["frames"] == 1200


@pytest.mark.ray_cluster
def test_no_address_starts_a_local_instance_even_beside_a_running_cluster(ray_cluster, monkeypatch):
    """Ray's own ``address=None`` joins the cluster that ``RAY_ADDRESS`` or ``ray start`` names; a sweep without
    ``--address`` starts a new local instance, as its help says (and two sweeps on one machine stay apart)."""
    from sb3_collapse.sweep.cluster import ray_session

    monkeypatch.setenv("RAY_ADDRESS", ray_cluster["address"])
    with ray_session(num_cpus=1) as ray:
        assert ray.cluster_resources()["CPU"] == 1  # the cluster has 2
        assert ray.get_runtime_context().gcs_address != ray_cluster["address"]
