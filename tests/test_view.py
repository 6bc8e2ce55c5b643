"""`adamimic view`: the browser viewer serves an export's live chain and a keyframes dataset on a loopback port,
answers over HTTP, and stops; the live chain stands, goes and hands over."""

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _serves(path, tmp_path):
    port = _free_port()
    log = open(tmp_path / "view.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "view", str(path), "--port", str(port)],
                            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        deadline, body = time.monotonic() + 90, None
        while time.monotonic() < deadline and proc.poll() is None:
            # the web server answers while the viewer is still loading: wait for the line that says it serves
            if "adamimic view: serving" not in (tmp_path / "view.log").read_text():
                time.sleep(0.5)
                continue
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as reply:
                    body = reply.read().decode(errors="replace")
                break
            except OSError:
                time.sleep(0.5)
        assert body is not None, (tmp_path / "view.log").read_text()
        assert "<html" in body.lower()
        assert proc.poll() is None  # still serving
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    return (tmp_path / "view.log").read_text()


def test_serves_an_exports_chain_and_stops(tmp_path):
    from test_chain import chained_export, standin_task_export

    export = chained_export(standin_task_export(tmp_path / "task"), tmp_path / "export",
                            balance=REPO / "models" / "pretrained" / "balance" / "export")
    text = _serves(export, tmp_path)
    assert "http://127.0.0.1:" in text


def test_the_live_chain_stands_goes_and_hands_over(tmp_path):
    from test_chain import chained_export, standin_task_export

    from pipeline.export.chain import ChainRunner, LiveChain

    export = chained_export(standin_task_export(tmp_path / "task"), tmp_path / "export", stand_s=0.2,
                            balance=REPO / "models" / "pretrained" / "balance" / "export")
    live = LiveChain(ChainRunner(export), 1.4)
    for _ in range(100):  # 0.5 s of physics without a go: still standing
        live.step()
    assert live.stretch == "stand" and "press go" in live.status()
    live.go()
    for _ in range(4 * 60):
        live.step()
        if live.stretch == "balance":
            break
    assert live.stretch == "balance" and live.end.startswith("the task ended")
    live.restart(1.2)
    assert live.stretch == "stand" and live.psi == 1.2 and live.data.qvel.max() == 0.0


def test_a_path_that_is_nothing_to_view_is_refused(tmp_path, capsys):
    from pipeline.cli import main

    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as exit_:
        main(["view", str(tmp_path / "empty"), "--port", str(_free_port())])
    assert exit_.value.code == 2 and "not an export folder" in capsys.readouterr().err


def test_serves_a_keyframes_dataset_and_a_retargeted_motion(tmp_path):
    from test_export import _tracking_data

    from pipeline.keyframes.datasets import write_tracking_dataset
    from pipeline.motion.dataset import write_motions

    data = _tracking_data()
    write_tracking_dataset(tmp_path / "keyframes" / "t" / "d_edit", data)
    _serves(tmp_path / "keyframes" / "t" / "d_edit", tmp_path)
    write_motions(tmp_path / "retargeted" / "t" / "motion", [data.motion])
    _serves(tmp_path / "retargeted" / "t", tmp_path)
