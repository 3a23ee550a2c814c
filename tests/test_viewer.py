"""Meshcat viewer: loopback-only live server, self-contained HTML replay, and both checked in headless Chromium.

The browser tests need Chromium (Debian's ``chromium`` package); without it they skip, except under
``CI=true`` where they fail.
"""

from __future__ import annotations

import argparse
import base64
import io
import ipaddress
import json
import os
import re
import socket
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import umsgpack

from robotdemo.assets import ROBOT_URDF, urdf_path
from robotdemo.scene import Scene, SceneConfig
from robotdemo.viewer import (Recorder, SceneViewer, ViewerConfig, ViewerUnavailable, add_viewer_arguments,
                              start_viewer, urdf_visuals, viewer_config_from_args)

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
ROBOT_LINKS = sorted({v.link for v in urdf_visuals(urdf_path(ROBOT_URDF))})


@pytest.fixture(scope="module")
def scene():
    with Scene(SceneConfig(n_objects=3, seed=1)) as s:
        yield s


def _taxels(scale: float) -> np.ndarray:
    return scale * np.linspace(0.0, 1.0, 16).reshape(4, 4)


# -- where the server listens ---------------------------------------------------------------------------------

def _listening_sockets(pid: int) -> list[tuple[str, int]]:
    """(address, port) of every TCP socket in LISTEN state that process ``pid`` holds (Linux /proc)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            match = re.fullmatch(r"socket:\[(\d+)\]", os.readlink(fd))
        except OSError:
            continue
        if match:
            inodes.add(match.group(1))
    found = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not Path(table).exists():
            continue
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            local, state, inode = fields[1], fields[3], fields[9]
            if state != "0A" or inode not in inodes:      # 0A: LISTEN
                continue
            ip_hex, port_hex = local.split(":")
            raw = bytes.fromhex(ip_hex)
            if len(raw) == 4:
                address = str(ipaddress.IPv4Address(raw[::-1]))
            else:
                address = str(ipaddress.IPv6Address(b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4))))
            found.append((address, int(port_hex, 16)))
    return found


def _web_port(url: str) -> int:
    return int(re.match(r"https?://[^/]*:(\d+)/", url).group(1))


needs_proc = pytest.mark.skipif(not Path("/proc/net/tcp").exists() and not IN_CI,  # in CI: run, and fail
                                reason="reads listening sockets from Linux /proc")


@needs_proc
def test_live_server_listens_on_loopback_only_and_close_stops_it(scene):
    viewer = SceneViewer(ViewerConfig())
    try:
        assert viewer.url.startswith("http://127.0.0.1:")
        sockets = _listening_sockets(viewer.server_pid)
        web_port = _web_port(viewer.url)
        assert ("127.0.0.1", web_port) in sockets
        assert len(sockets) == 2, sockets                       # the web page and the ZMQ command port
        assert all(address == "127.0.0.1" for address, _ in sockets), sockets
        opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
        with opener.open(viewer.url, timeout=10) as response:
            assert b"MeshCat.Viewer" in response.read()
        assert viewer.update(scene, _taxels(0.5), force=True)
    finally:
        viewer.close()
    assert viewer._server.proc.poll() is not None               # the process is gone
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", web_port), timeout=2).close()
    viewer.close()                                               # idempotent


@needs_proc
def test_host_override_exposes_web_port_with_a_warning_but_keeps_zmq_on_loopback(capsys):
    with SceneViewer(ViewerConfig(host="0.0.0.0")) as viewer:
        assert "warning" in capsys.readouterr().err
        sockets = _listening_sockets(viewer.server_pid)
        web_port = _web_port(viewer.url)
        assert ("0.0.0.0", web_port) in sockets
        assert [a for a, p in sockets if p != web_port] == ["127.0.0.1"], sockets


def test_loopback_default_prints_no_warning(capsys):
    with SceneViewer(ViewerConfig()):
        pass
    assert "warning" not in capsys.readouterr().err


def test_server_that_cannot_start_raises_viewer_unavailable(monkeypatch):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(ViewerUnavailable, match="could not start"):
            SceneViewer(ViewerConfig(port=port))
    with pytest.raises(ViewerUnavailable, match="not an IP address"):
        SceneViewer(ViewerConfig(host="no such host"))
    monkeypatch.setattr(sys, "executable", "/nonexistent/python3")
    with pytest.raises(ViewerUnavailable, match="cannot start"):
        SceneViewer(ViewerConfig())


def test_start_viewer_falls_back_to_recording_only(capsys, scene):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        viewer = start_viewer(ViewerConfig(port=busy.getsockname()[1], record=True))
    assert viewer is not None and viewer.url is None and viewer.recording
    assert "recording only" in capsys.readouterr().err
    viewer.close()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        assert start_viewer(ViewerConfig(port=busy.getsockname()[1])) is None
    assert "running headless" in capsys.readouterr().err
    assert start_viewer(None) is None


def test_ctrl_c_in_a_terminal_stops_the_demo_quickly_and_keeps_the_replay(tmp_path):
    """Ctrl-C goes to the terminal's whole process group. The Meshcat server runs in a session of its own, so
    the demo, not the signal, stops it: the run ends at once with the replay written and no "stopped
    answering" warning. Before, the server died with the demo and the demo's last update waited 3 s for it."""
    import signal
    import subprocess

    replay = tmp_path / "run.html"
    err_path, out_path = tmp_path / "err.txt", tmp_path / "out.txt"
    with open(err_path, "w") as err, open(out_path, "w") as out:
        demo = subprocess.Popen([sys.executable, "-m", "robotdemo", "demo", "--objects", "3", "--meshcat",
                                 "--record", str(replay)], stdout=out, stderr=err,
                                start_new_session=True)  # its own process group, as a terminal gives a job
    try:
        deadline = time.monotonic() + 120
        while "Meshcat viewer at" not in err_path.read_text():
            assert demo.poll() is None and time.monotonic() < deadline, err_path.read_text()
            time.sleep(0.1)
        time.sleep(1.0)  # sorting is under way
        start = time.monotonic()
        os.killpg(demo.pid, signal.SIGINT)
        code = demo.wait(timeout=30)
        after_s = time.monotonic() - start
        assert code == 130, (f"exit code {code} {after_s:.1f} s after SIGINT; the demo's stderr:\n"
                             f"{err_path.read_text()}\nits stdout:\n{out_path.read_text()}")
        assert after_s < 3.0
    finally:
        if demo.poll() is None:
            demo.kill()
    text = err_path.read_text()
    assert "robotdemo: interrupted" in text and "stopped answering" not in text, text
    assert replay.is_file() and replay.stat().st_size > 10_000


def test_cli_arguments_map_to_a_config():
    parser = argparse.ArgumentParser()
    add_viewer_arguments(parser)
    assert viewer_config_from_args(parser.parse_args([])) is None
    live = viewer_config_from_args(parser.parse_args(["--meshcat"]))
    assert live.live and live.host == "127.0.0.1" and not live.record
    exposed = viewer_config_from_args(parser.parse_args(["--meshcat-host", "0.0.0.0", "--meshcat-port", "7100"]))
    assert exposed.live and exposed.host == "0.0.0.0" and exposed.port == 7100
    record = viewer_config_from_args(parser.parse_args(["--record-html", "run.html", "--viewer-rate", "30"]))
    assert record.record and not record.live and record.record_fps == 30


# -- throttling and recording ---------------------------------------------------------------------------------

def test_fast_transform_packing_is_byte_identical_to_meshcats():
    from meshcat.commands import SetTransform
    from meshcat.path import Path as MeshcatPath

    from robotdemo.viewer import _pack_set_transform

    matrix = np.round(np.random.default_rng(0).normal(size=(4, 4)), 6)
    for path in ("/meshcat/robot/link1", "/meshcat/labels/" + "x" * 40, "/meshcat/" + "y" * 300):
        expected = umsgpack.packb(SetTransform(matrix, MeshcatPath(tuple(path.split("/")[1:]))).lower())
        assert _pack_set_transform(path, matrix) == expected


def test_update_throttles_to_the_configured_rate(scene):
    def run(viewer, ticks=1000):        # 1 s of simulated time at the 1 kHz control rate
        drawn = 0
        for _ in range(ticks):
            scene.sim.step()
            drawn += viewer.update(scene, _taxels(1.0))
        return drawn

    with SceneViewer(ViewerConfig(rate_hz=25.0, record=True, record_fps=25.0)) as viewer:
        assert 25 <= run(viewer) <= 26
        assert 25 <= viewer.recorded_frames <= 26
    recorder = Recorder(fps=20.0)
    assert 20 <= run(recorder) <= 21 and 20 <= recorder.recorded_frames <= 21
    with pytest.raises(ValueError, match="16 values"):
        Recorder().update(scene, np.zeros(9))


def test_taxel_forces_given_as_a_callable_are_computed_only_for_drawn_frames(scene):
    calls = []

    def taxels():
        calls.append(scene.sim.time_s)
        return _taxels(2.0)

    recorder = Recorder(fps=20.0)
    drawn = 0
    for _ in range(1000):
        scene.sim.step()
        drawn += recorder.update(scene, taxels)
    assert len(calls) == drawn and 20 <= drawn <= 21
    np.testing.assert_array_equal(recorder._taxels, np.asarray(_taxels(2.0)).reshape(4, 4))


def test_a_new_scene_replaces_the_old_one_and_restarts_the_recording(tmp_path):
    recorder = Recorder(fps=25)
    for seed in (2, 3):
        with Scene(SceneConfig(n_objects=2, seed=seed)) as s:
            for _ in range(200):
                s.sim.step()
                recorder.update(s)
            names = [o.name for o in s.objects]
    assert recorder.recorded_frames == 5                          # 0.2 s of the second scene only
    drawn = {c["path"].split("/")[3] for c in _commands(recorder.static_html())
             if c["type"] == "set_object" and c["path"].startswith("/meshcat/objects/")}
    assert drawn == set(names)


def _commands(html: str) -> list[dict]:
    block = re.search(r"var commands = \[(.*?)\];", html, re.S).group(1)
    return [umsgpack.unpackb(base64.b64decode(s)) for s in re.findall(r'"([A-Za-z0-9+/=]+)"', block)]


def test_recording_writes_a_self_contained_replay_with_robot_objects_labels_and_heat_map(scene, tmp_path):
    recorder = Recorder(fps=25)
    assert recorder.url is None                                 # no server needed for recording
    with pytest.raises(ValueError, match="update"):
        recorder.write_html(tmp_path / "nothing.html")
    first = scene.objects[0]
    for tick in range(400):
        scene.sim.step()
        labels = {first.name: first.category} if tick >= 200 else {}
        recorder.update(scene, _taxels(tick / 400), labels)
    target = tmp_path / "out" / "replay.html"
    target.parent.mkdir()
    target.write_text("old contents")
    assert recorder.write_html(target) == target
    assert sorted(p.name for p in target.parent.iterdir()) == ["replay.html"]   # replaced in place, no temp left
    html = target.read_text(encoding="utf-8")
    assert "<script src" not in html and "MeshCat.Viewer" in html

    commands = _commands(html)
    objects = {c["path"] for c in commands if c["type"] == "set_object"}
    for link in ROBOT_LINKS:
        assert f"/meshcat/robot/{link}/visual0" in objects
    for obj in scene.objects:
        assert f"/meshcat/objects/{obj.name}/shape" in objects
    assert f"/meshcat/labels/{first.name}/{first.category}/text" in objects
    assert {f"/meshcat/taxels/cell{r}{c}" for r in range(4) for c in range(4)} <= objects
    assert {"/meshcat/zones/combustible/name", "/meshcat/zones/noncombustible/name"} <= objects

    (animation,) = [c for c in commands if c["type"] == "set_animation"]
    assert commands[-1] is animation                            # after the objects it animates
    clips = {a["path"]: a["clip"] for a in animation["animations"]}
    assert clips["/meshcat/robot/link1"]["fps"] == 25
    visible = next(t for t in clips[f"/meshcat/labels/{first.name}/{first.category}"]["tracks"] if t["name"] == ".visible")
    assert visible["keys"][0] == {"time": 0, "value": False} and visible["keys"][-1]["value"] is True
    colour = clips["/meshcat/taxels/cell33/<object>"]["tracks"][0]
    assert colour["name"] == ".material.color" and colour["keys"][0]["value"] != colour["keys"][-1]["value"]
    assert 9 <= colour["keys"][-1]["time"] <= 10                 # 0.4 s at 25 fps, in frames


# -- in a browser ---------------------------------------------------------------------------------------------

def _chromium() -> str:
    from robotdemo.viewer_browser import find_chromium

    path = find_chromium()
    if path is None:
        message = "Chromium not found: install Debian's 'chromium' package (or set $CHROMIUM)"
        if IN_CI:
            pytest.fail(message)
        pytest.skip(message)
    return path


@pytest.fixture(scope="module")
def browser():
    from robotdemo.viewer_browser import HeadlessChromium

    with HeadlessChromium(_chromium(), width=960, height=640, timeout_s=30) as b:
        yield b


def _changed_fraction(png_a: bytes, png_b: bytes) -> float:
    from PIL import Image, ImageChops

    a = Image.open(io.BytesIO(png_a)).convert("RGB")
    b = Image.open(io.BytesIO(png_b)).convert("RGB")
    diff = np.asarray(ImageChops.difference(a, b)).max(axis=2)     # per pixel, the most changed channel
    return float((diff > 24).mean())


def _check_rendered(browser) -> None:
    """The canvas is not blank: the scene shows, and hiding the robot (or the objects) changes many pixels."""
    from PIL import Image

    from robotdemo.viewer_browser import NEXT_FRAME_JS

    time.sleep(0.3)
    browser.evaluate(NEXT_FRAME_JS)
    full = browser.screenshot_png()
    pixels = np.asarray(Image.open(io.BytesIO(full)).convert("RGB"), dtype=float)
    assert pixels.std() > 20 and len(np.unique(pixels.reshape(-1, 3), axis=0)) > 200
    for part, least in (("robot", 0.01), ("objects", 0.002)):
        browser.evaluate(f'viewer.scene_tree.find(["meshcat", "{part}"]).object.visible = false; true')
        browser.evaluate(NEXT_FRAME_JS)
        without = browser.screenshot_png()
        browser.evaluate(f'viewer.scene_tree.find(["meshcat", "{part}"]).object.visible = true; true')
        browser.evaluate(NEXT_FRAME_JS)
        assert _changed_fraction(full, without) > least, part       # about 2.8 % and 0.6 % at 960 x 640


def _expected_meshes(scene) -> list[str]:
    return ([f"/meshcat/robot/{link}/visual0/" for link in ROBOT_LINKS]
            + [f"/meshcat/objects/{obj.name}/shape/" for obj in scene.objects]
            + ["/meshcat/table/table_top/visual0/", "/meshcat/taxels/cell00/"])


def test_browser_shows_live_scene_and_labels_as_they_arrive(browser, scene):
    from robotdemo.viewer_browser import wait_for_meshcat_scene

    with SceneViewer(ViewerConfig()) as viewer:
        viewer.update(scene, _taxels(0.8), force=True)
        browser.open(viewer.url)
        paths = wait_for_meshcat_scene(browser, _expected_meshes(scene))
        assert set(_expected_meshes(scene)) <= set(paths)
        assert not any(p.startswith("/meshcat/labels/") for p in paths)

        first = scene.objects[0]
        viewer.update(scene, _taxels(0.8), labels={first.name: "wood"}, force=True)
        wait_for_meshcat_scene(browser, [f"/meshcat/labels/{first.name}/wood/text"], timeout_s=10)
        _check_rendered(browser)


def test_browser_plays_recorded_html_without_a_server(browser, scene, tmp_path):
    from robotdemo.viewer_browser import wait_for_meshcat_scene

    first = scene.objects[0]
    recorder = Recorder(fps=25)
    for tick in range(500):
        scene.sim.step()
        recorder.update(scene, _taxels(tick / 500), {first.name: "metal"} if tick >= 250 else {})
    path = recorder.write_html(tmp_path / "replay.html")
    browser.open(path.as_uri())
    paths = wait_for_meshcat_scene(browser, _expected_meshes(scene))
    assert set(_expected_meshes(scene)) <= set(paths)

    label = json.dumps(["meshcat", "labels", first.name, "metal"])
    cell = json.dumps(["meshcat", "taxels", "cell33", "<object>"])
    state = (f"(() => {{ viewer.animator.seek(%s); return [viewer.scene_tree.find({label}).object.visible,"
             f" viewer.scene_tree.find({cell}).object.material.color.getHex()]; }})()")
    assert browser.evaluate("viewer.animator.actions.length > 0 && viewer.animator.duration > 0.3")
    browser.evaluate("viewer.animator.pause(); true")
    visible_start, colour_start = browser.evaluate(state % "0")
    visible_end, colour_end = browser.evaluate(state % "viewer.animator.duration")
    assert (visible_start, visible_end) == (False, True)        # the label appears once known
    assert colour_start != colour_end                           # the heat map follows the pressures
    _check_rendered(browser)
