"""The viewers: the meshcat server's lifecycle and binding, the map view's scene against the map, the frame
view's drawings and the notebook app driven without a browser.

What the browser receives is checked by decoding the server's own copy of the scene (``static_html`` holds
every command the server replays to a connecting browser), not the view's bookkeeping alone.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pycolmap
import pytest

pytest.importorskip("meshcat")
pytest.importorskip("ipywidgets")
psutil = pytest.importorskip("psutil")
import umsgpack  # noqa: E402

from slamkit.config import SlamConfig  # noqa: E402
from slamkit.pipeline import Slam  # noqa: E402
from slamkit.sources import open_source  # noqa: E402
from slamkit.viz import frame_view as fv  # noqa: E402
from slamkit.viz.explain import describe_step  # noqa: E402
from slamkit.viz.meshcat_view import MapState, MapView, recency_colors, state_from_run  # noqa: E402
from slamkit.viz.server import HOST, MeshcatServer  # noqa: E402

pycolmap.logging.minloglevel = 2

FAST = dict(frame_skip=2, init_frames=10, max_frames=40, num_features=1000)
"""A short run of the default sequence: 40 frames, about 10 keyframes, a few seconds."""


# ---------------------------------------------------------------------------------------------- helpers


def scene_objects(view: MapView | str) -> dict[str, dict]:
    """Path -> decoded set_object command, for every object the server would replay to a browser (from the
    view's static HTML, or an exported HTML text); ``"__properties__"``: path -> {property: value}."""
    html = view if isinstance(view, str) else view.static_html()
    out: dict[str, dict] = {}
    props: dict[str, dict] = {}
    for m in re.finditer(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)", html):
        cmd = umsgpack.unpackb(base64.b64decode(m.group(1)))
        if cmd["type"] == "set_object":
            out[cmd["path"]] = cmd
        elif cmd["type"] == "set_property":
            props.setdefault(cmd["path"], {})[cmd["property"]] = cmd["value"]
    out["__properties__"] = props
    return out


def attribute(obj: dict, name: str) -> np.ndarray:
    """A geometry attribute of a decoded set_object as (itemSize, N) float32 (meshcat packs 3xN column-major)."""
    geom = obj["object"]["geometries"][0]["data"]["attributes"][name]
    arr = np.frombuffer(geom["array"].data, np.float32)
    assert geom["type"] == "Float32Array"
    return arr.reshape(-1, geom["itemSize"]).T


def listening(pid: int) -> list:
    return [c for c in psutil.Process(pid).net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]


def proc_net_listeners(port: int) -> list[str]:
    """Local addresses listening on ``port`` in /proc/net/tcp and tcp6 (hex ip:port, state 0A = LISTEN)."""
    found = []
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not os.path.exists(name):
            continue
        for line in open(name).read().splitlines()[1:]:
            parts = line.split()
            ip, p = parts[1].split(":")
            if int(p, 16) == port and parts[3] == "0A":
                found.append(f"{name}:{ip}")
    return found


# ---------------------------------------------------------------------------------------------- server


def test_server_listens_on_loopback_only_and_stops_on_close():
    server = MeshcatServer()
    try:
        zmq_port, web_port = server.ports
        assert server.web_url == f"http://{HOST}:{web_port}/static/"
        assert server.zmq_url == f"tcp://{HOST}:{zmq_port}"
        socks = listening(server.pid)
        assert {c.laddr.port for c in socks} == {zmq_port, web_port}
        assert all(c.laddr.ip == "127.0.0.1" for c in socks), socks
        for port in (zmq_port, web_port):
            # nothing on 0.0.0.0 / :: — only 0100007F (127.0.0.1) in /proc/net/tcp
            assert proc_net_listeners(port) == ["/proc/net/tcp:0100007F"], proc_net_listeners(port)
        import urllib.request

        assert urllib.request.urlopen(server.web_url, timeout=10).status == 200
        vis = server.visualizer()
        vis["probe"].set_transform(np.eye(4))  # the zmq side answers
    finally:
        server.close()
    assert not server.alive
    assert not psutil.pid_exists(server.pid) or psutil.Process(server.pid).status() == psutil.STATUS_ZOMBIE
    assert proc_net_listeners(web_port) == [] and proc_net_listeners(zmq_port) == []
    server.close()  # idempotent


def test_server_is_stopped_when_its_owner_is_garbage_collected_or_killed():
    import gc

    server = MeshcatServer()
    pid = server.pid
    del server
    gc.collect()
    assert _gone_within(pid, 5.0)
    # a kernel killed with SIGKILL runs no atexit handler: the server notices its parent is gone
    code = textwrap.dedent("""
        import sys, time
        from slamkit.viz.server import MeshcatServer
        s = MeshcatServer()
        print(s.pid, flush=True)
        time.sleep(60)
    """)
    owner = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        child = int(owner.stdout.readline())
        assert psutil.pid_exists(child)
        owner.send_signal(signal.SIGKILL)
        owner.wait(10)
        assert _gone_within(child, 10.0), "the meshcat server outlived its killed owner"
    finally:
        owner.kill()


def _gone_within(pid: int, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if not psutil.pid_exists(pid) or psutil.Process(pid).status() == psutil.STATUS_ZOMBIE:
            return True
        time.sleep(0.1)
    return False


# ---------------------------------------------------------------------------------------------- a real run


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A short SLAM run of the default sequence drawn by a MapView after every step, then saved."""
    slam = Slam(open_source("default"), SlamConfig().with_overrides(**FAST))
    view = MapView()
    drawn = []  # (result.matches, lines derived by the frame view) of tracked frames
    tracked = []  # the tracked steps' results
    stats = []

    def record(s, r):
        stats.append((r.is_keyframe or r.status == "initialized", view.stats.mode, view.objects_sent_total,
                      view.reframes, view.newest_on_screen()))

    local_map = None
    slam.callbacks.append(view.on_step)
    slam.callbacks.append(record)
    while not slam.done:
        r = slam.step()
        if r.status == "tracked":
            lines = fv.flow_lines(r)  # what the result carries: the tracker's own matches
            drawn.append((r.matches, len(lines[0]), len(lines[1])))
            tracked.append(r)
        local_map = slam.local_map
    assert local_map is not None
    slam.finish()
    view.update(slam)
    out = tmp_path_factory.mktemp("run") / "run"
    slam.save(out)
    yield dict(slam=slam, view=view, drawn=drawn, stats=stats, dir=out, tracked=tracked)
    view.close()


def test_map_view_scene_matches_the_map(run):
    slam, view = run["slam"], run["view"]
    m = slam.slam_map
    ids, xyz, rgb = m.point_cloud()
    counts = view.scene_counts()
    assert m.num_keyframes >= 6 and m.num_points > 500
    assert counts["points"] == m.num_points
    assert np.array_equal(view.point_ids(), np.sort(ids))
    assert counts["keyframes"] == m.num_keyframes
    assert counts["path"] == len(slam.trajectory())
    # after finish() (a global BA that moves every pose) the current frame sits at the last frame's final pose
    assert counts["current"] == 1
    final = np.linalg.inv(slam.pose_of(len(slam.records) - 1))
    assert np.allclose(view._map.current, final)
    assert np.linalg.norm(final[:3, 3] - slam.trajectory().positions[-1]) < 1e-9
    marker = scene_objects(view)["__properties__"]
    assert marker.get("/meshcat/slamkit/current/frame", {}).get("visible", True) is True

    scene = scene_objects(view)
    groups = {p: o for p, o in scene.items() if p.startswith("/meshcat/slamkit/points/")}
    assert len(groups) == counts["point_groups"]
    intro = view.point_introductions()
    by_id = dict(zip(ids.tolist(), xyz))
    extent = np.ptp(xyz, axis=0).max()
    total = 0
    for path, obj in groups.items():
        assert obj["object"]["object"]["type"] == "Points"
        pos, col = attribute(obj, "position"), attribute(obj, "color")
        assert pos.shape[0] == 3 and col.shape == pos.shape  # 3xN, not Nx3
        assert col.min() >= 0.0 and col.max() <= 1.0 and col.max() > 0.05  # floats in [0, 1], not uint8
        k = int(path.rsplit("kf", 1)[1])
        members = sorted(p for p, i in intro.items() if i == k)
        assert pos.shape[1] == len(members)
        want = np.array([by_id[p] for p in members])
        # what the browser holds is what was last sent: within the move tolerance of the map
        assert np.abs(pos.T - want).max() <= 3 * view.move_tolerance * extent + 1e-5
        total += pos.shape[1]
    assert total == m.num_points

    frustums = scene["/meshcat/slamkit/keyframes/geom"]
    v, c = attribute(frustums, "position"), attribute(frustums, "color")
    assert v.shape == (3, 16 * m.num_keyframes) and c.shape == v.shape
    assert c.min() >= 0 and c.max() <= 1
    first, last = c[:, 0], c[:, -1]
    assert first[1] > 0.8 and first[0] < 0.1  # green
    assert last[0] > 0.8 and last[1] < 0.1  # red
    # apexes of the frustums are the keyframe centres
    centres = np.array([m.reconstruction.image(i).projection_center() for i in sorted(m.keyframes)])
    assert np.allclose(v[:, ::16].T, centres, atol=1e-4 * extent + 1e-5)
    path = attribute(scene["/meshcat/slamkit/path/geom"], "position")
    assert path.shape == (3, 2 * (len(slam.trajectory()) - 1))


def test_updates_are_incremental_during_the_run(run):
    stats = run["stats"]
    assert all(s[1] == "full" for s in stats if s[0])  # a small map is read whole (exact)
    # non-keyframe steps send no object (the current frame only moves: set_transform), unless the view
    # reframed to follow the camera
    sent = np.diff([0] + [s[2] for s in stats])
    reframed = np.diff([0] + [s[3] for s in stats]) > 0
    kf = np.array([s[0] for s in stats])
    assert (sent[~kf & ~reframed] == 0).all() and (sent[kf] > 0).all()
    assert 1 <= reframed.sum() <= 0.25 * len(stats)  # it followed the camera, a few times, not every frame


def test_the_view_follows_the_camera(run):
    """After every step the current frame, the newest keyframe and the newest path frame are inside the
    middle of the viewer as its camera was last set (the legend is under the viewer, never over it);
    without following, the camera of this run leaves the view."""
    from slamkit.viz.meshcat_view import FOLLOW_BOX

    on_screen = [s[4] for s in run["stats"] if len(s[4])]
    assert len(on_screen) >= 30
    worst = max(float(np.abs(ndc).max()) for ndc in on_screen)
    assert worst <= FOLLOW_BOX, worst
    slam = Slam(open_source("default"), SlamConfig().with_overrides(**FAST))
    still = MapView(server=run["view"].server, name="still")
    still.follow = False
    slam.callbacks.append(still.on_step)
    while not slam.done:
        slam.step()
    assert float(np.abs(still.newest_on_screen()).max()) > 1.0  # the camera left the view it was framed in
    assert 'class="slamkit-legend"' in still.iframe_html() and "position:absolute;bottom" not in still.iframe_html()


def test_frame_view_draws_the_tracked_matches_the_result_carries(run):
    drawn = np.array(run["drawn"], int)
    assert len(drawn) >= 10
    assert (drawn[:, 1] == drawn[:, 0]).all() and (drawn[:, 2] == drawn[:, 0]).all()  # exactly the flow score's


def test_load_saved_run_and_export_html(run, tmp_path):
    slam = run["slam"]
    state = state_from_run(run["dir"])
    assert np.array_equal(state.keyframe_ids, np.array(sorted(slam.slam_map.keyframes)))
    assert np.allclose(state.keyframe_times, [slam.slam_map.keyframes[i].timestamp for i in state.keyframe_ids])
    loaded = MapView()  # a server of its own
    try:
        stats = loaded.load_run(run["dir"])
        assert stats.mode == "full"
        assert loaded.scene_counts()["points"] == slam.slam_map.num_points
        assert loaded.scene_counts()["keyframes"] == slam.slam_map.num_keyframes
        out = loaded.export_html(tmp_path / "report" / "map.html")
        text = out.read_text()
        assert text.lstrip().startswith("<!DOCTYPE html>") and "MeshCat.Viewer" in text
        exported = scene_objects(text)
        n = sum(attribute(o, "position").shape[1] for p, o in exported.items() if "/slamkit/points/" in p)
        assert n == slam.slam_map.num_points
    finally:
        loaded.close()


def test_another_path_through_the_map(run):
    """add_path draws another walk through the map shown (issue 49: a second walk localized in a saved run's map):
    its line and a dot at every frame at exactly the given map positions, in its colour, under the view's transform
    like the map's own path; the legend and the picture list it; Reset camera frames it with the map, even where it
    leaves the map's box; hidden with the path; gone when another map is shown."""
    from matplotlib.figure import Figure

    from slamkit.viz.server import ViewerError
    from slamkit.viz.static_twin import _project, draw_map_from_camera, map_picture

    view = MapView(server=run["view"].server, name="other-path")
    with pytest.raises(ViewerError, match="no map shown yet"):
        view.add_path(np.zeros((3, 3)), "too early")
    view.load_run(run["dir"])
    extent = view._map.map_extent
    walk = run["slam"].trajectory().positions[::2] + np.array([0.8 * extent, 0.0, 0.0])  # partly beside the map
    color = (0.2, 0.4, 0.6)
    view.add_path(walk, "second walk", color)
    scene = scene_objects(view)
    line, dots = scene["/meshcat/other-path/path/other0/line"], scene["/meshcat/other-path/path/other0/dots"]
    v = attribute(line, "position").T
    assert v.shape == (2 * (len(walk) - 1), 3)
    assert np.allclose(v[0::2], walk[:-1], atol=1e-6 * extent) and np.allclose(v[1::2], walk[1:], atol=1e-6 * extent)
    assert np.allclose(attribute(line, "color").T, color, atol=1e-6)
    assert np.allclose(attribute(dots, "position").T, walk, atol=1e-6 * extent)
    assert np.allclose(attribute(dots, "color").T, color, atol=1 / 255)
    assert view.scene_counts()["other_paths"] == 1
    assert view.legend_items()[-1] == ("#336699", "second walk") and "second walk" in view.iframe_html()
    # framed with the map: every frame of the walk in front of the home camera and inside the viewer
    view.reset_camera()
    T = view.display_from_map
    ndc, depth = _project(walk @ T[:3, :3].T + T[:3, 3], np.asarray(view._out.camera_position, float), view.aspect)
    assert (depth > 0).all() and np.abs(ndc).max() <= 1.0, np.abs(ndc).max()
    assert draw_map_from_camera(Figure().add_subplot(), view)["other_paths"] == len(walk)
    assert map_picture(view, 300)[:4] == b"\x89PNG"
    # hidden with the path: neither the legend nor the picture lists it
    view.configure(show_path=False)
    assert all(isinstance(k, str) for k in view.legend_items())
    assert draw_map_from_camera(Figure().add_subplot(), view)["other_paths"] == 0
    view.configure(show_path=True)
    # another map: the walk belonged to the map it was drawn through
    view.show(state_from_run(run["dir"]))  # read again: another Reconstruction, another map
    assert not any("/path/other" in p for p in scene_objects(view))
    assert view.scene_counts().get("other_paths", 0) == 0 and "second walk" not in view.iframe_html()


def test_view_settings_clip_track_and_toggles(run):
    slam, view = run["slam"], run["view"]
    m = slam.slam_map
    kf = sorted(m.keyframes)
    try:
        lo, hi = kf[2], kf[4]
        view.configure(clip=(lo, hi))
        intro = view.point_introductions()
        want = sum(1 for i in intro.values() if lo <= i <= hi)
        counts = view.scene_counts()
        assert counts["points"] == want and 0 < want < m.num_points
        assert counts["keyframes"] == 3
        groups = [p for p in scene_objects(view) if p.startswith("/meshcat/slamkit/points/")]
        assert sorted(int(p.rsplit("kf", 1)[1]) for p in groups) == sorted({i for i in intro.values()
                                                                          if lo <= i <= hi})
        view.configure(clip=None)
        assert view.scene_counts()["points"] == m.num_points

        # a track: lines from the point to every keyframe observing it
        pid = max(intro, key=lambda p: len(m.reconstruction.point3D(p).track.elements))
        observers = {el.image_id for el in m.reconstruction.point3D(pid).track.elements} & set(kf)
        view.configure(track_point=pid)
        assert view.scene_counts()["track"] == len(observers) >= 2
        lines = attribute(scene_objects(view)["/meshcat/slamkit/track/lines"], "position")
        assert lines.shape == (3, 2 * len(observers))
        assert np.allclose(lines[:, ::2].T, m.reconstruction.point3D(pid).xyz, atol=1e-3)
        view.configure(track_point=-1)
        assert view.scene_counts()["track"] == 0

        view.configure(show_points=False, show_directions=True, background="#203040")
        props = scene_objects(view)["__properties__"]
        assert props["/meshcat/slamkit/points"]["visible"] is False
        assert props["/meshcat/slamkit/directions"]["visible"] is True
        bg = scene_objects(view)["/meshcat/background"]["object"]["materials"][0]
        assert bg["color"] == 0x203040
    finally:
        view.configure(show_points=True, show_directions=False, background="#ffffff", clip=None, track_point=-1)


def test_colors():
    c = recency_colors(np.linspace(0, 1, 5))
    assert c.dtype == np.float32 and c.shape == (5, 3)
    assert np.allclose(c[0], [0, 0.95, 0]) and np.allclose(c[-1], [0.95, 0, 0])
    assert c.min() >= 0 and c.max() <= 1


# ---------------------------------------------------------------------------------------------- incremental diff


def _synthetic_map(n_images: int, points_per_image: int, seed: int = 0):
    """A Reconstruction with ``n_images`` posed images along x, each introducing points seen by it and the
    next image (ids assigned in order, as the mapper does)."""
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[500, 500, 320, 240], camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    for i in range(1, n_images + 1):
        _add_image(rec, i, 2 * points_per_image + 10)
    for i in range(1, n_images):
        _add_points(rec, rng, i, points_per_image)
    return rec, rng


def _add_image(rec, i: int, n_kp: int) -> None:
    im = pycolmap.Image(name=f"im{i}", keypoints=np.zeros((n_kp, 2)), camera_id=1, image_id=i)
    rec.add_image_with_trivial_frame(im)
    rec.frame(i).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([-0.1 * i, 0.0, 0.0]))
    rec.register_frame(i)


def _add_points(rec, rng, i: int, n: int) -> list[int]:
    """Points observed by images i and i + 1 (keypoint slots 0..n-1 of i + 1, n..2n-1 of i)."""
    ids = []
    for j in range(n):
        track = pycolmap.Track()
        track.add_element(i, n + j)
        track.add_element(i + 1, j)
        xyz = np.array([0.1 * i + rng.uniform(-1, 1), rng.uniform(-1, 1), 3 + rng.uniform(-1, 1)])
        ids.append(rec.add_point3D(xyz, track, np.array([200, 100, 50], np.uint8)))
    return ids


def _state(rec, key):
    ids = np.array(sorted(rec.reg_image_ids()))
    centers = np.array([rec.image(i).projection_center() for i in ids])
    return MapState(rec, ids, ids * 0.1, ids * 0.1, centers, None, key=key)


def test_incremental_update_sends_only_changed_groups():
    server = MeshcatServer()
    try:
        view = MapView(server=server, full_read_points=0)  # force the incremental path even for small maps
        rec, rng = _synthetic_map(12, 50)
        key = object()
        st = view.show(_state(rec, key))
        assert st.mode == "full" and view.scene_counts()["points"] == 11 * 50
        assert view.scene_counts()["point_groups"] == 11  # introduced by images 2..12
        # nothing changed: no point group is sent
        st = view.show(_state(rec, key))
        assert (st.mode, st.chunks_sent, st.dirty_keyframes) == ("incremental", 0, 0)
        # a new keyframe with new points; the previous keyframe and its points move (a local BA)
        _add_image(rec, 13, 110)
        new = _add_points(rec, rng, 12, 50)
        rec.frame(12).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([-1.25, 0.0, 0.0]))
        moved = [p for p in rec.point3D_ids() if 12 in {el.image_id for el in rec.point3D(p).track.elements}
                 and p not in new]
        for p in moved[:5]:
            rec.point3D(p).xyz = rec.point3D(p).xyz + [0.01, 0, 0]
        # and one point of image 5 is filtered (deleted) after the adjustment
        victim = next(p for p in rec.point3D_ids() if {el.image_id for el in rec.point3D(p).track.elements} == {4, 5})
        rec.delete_point3D(victim)
        rec.frame(5).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([-0.51, 0.0, 0.0]))
        st = view.show(_state(rec, key))
        assert st.mode == "incremental"
        assert st.dirty_keyframes == 3  # 13 (new), 12 and 5 (moved)
        intro = view.point_introductions()
        assert {intro[p] for p in new} == {13}
        # groups re-sent: the new one (13), the one holding the moved points (12), the one that lost a point (5)
        assert st.chunks_sent == 3, st
        assert view.scene_counts()["points"] == rec.num_points3D() == 12 * 50 - 1
        for p in moved[:5]:
            assert np.allclose(view.point_positions([p])[0], rec.point3D(p).xyz, atol=1e-6)
        # a sub-tolerance move is not sent (and not forgotten: what is shown stays what was sent)
        rec.frame(12).rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.array([-1.26, 0.0, 0.0]))
        p = moved[0]
        rec.point3D(p).xyz = rec.point3D(p).xyz + [1e-7, 0, 0]
        st = view.show(_state(rec, key))
        assert st.chunks_sent == 0 and st.dirty_keyframes == 1
        # a point deleted where no dirty keyframe sees it: the count check reconciles
        victim = next(p for p in rec.point3D_ids() if {el.image_id for el in rec.point3D(p).track.elements} == {2, 3})
        rec.delete_point3D(victim)
        st = view.show(_state(rec, key))
        assert view.scene_counts()["points"] == rec.num_points3D() and st.chunks_sent == 1
        # tombstones of deleted points compact away without changing what is shown
        before = view.point_ids(), view.point_positions(view.point_ids())
        view._compact()
        assert np.array_equal(view.point_ids(), before[0])
        assert np.array_equal(view.point_positions(before[0]), before[1])
        st = view.show(_state(rec, key))
        assert st.chunks_sent == 0 and view.scene_counts()["points"] == rec.num_points3D()
        # another map (new segment / reset): everything is sent again
        rec2, _ = _synthetic_map(4, 20, seed=1)
        st = view.show(_state(rec2, object()))
        assert st.mode == "full" and view.scene_counts()["points"] == 60 and view.scene_counts()["point_groups"] == 3
        groups = [p for p in scene_objects(view) if p.startswith("/meshcat/slamkit/points/")]
        assert len(groups) == 3
    finally:
        server.close()


# ---------------------------------------------------------------------------------------------- drawings


def test_draw_flow_and_matches():
    img = np.full((120, 160, 3), 255, np.uint8)
    ref = np.array([[10.0, 10.0], [100.0, 50.0]])
    cur = np.array([[30.0, 12.0], [110.0, 80.0]])
    out = fv.draw_flow(img, ref, cur)
    assert out.shape == img.shape and out.dtype == np.uint8
    assert tuple(out[12, 30]) == fv.FLOW_DOT  # a dot at the current position
    assert (out != 255).any(axis=2)[11, 20]  # the line between them
    small = fv.draw_flow(img, ref, cur, width=80)
    assert small.shape == (60, 80, 3)
    both = fv.draw_matches(img, ref, img, cur, np.array([[0, 0], [1, 1]]))
    assert both.shape == (120, 320, 3)
    assert fv.encode_image(out)[:2] == b"\xff\xd8" and fv.encode_image(out, "png")[:4] == b"\x89PNG"


def test_picture_of_the_view_from_its_camera(run):
    """The 3D view's PNG twin (what a notebook opened untrusted or without its kernel shows) is the map seen from
    the viewer's own camera: three.js's camera at the position last sent, looking at the map's centre, z up, so
    a point to the camera's right is drawn right of centre and one above it above; every keyframe and most
    points are in the picture, and the picture has the viewer's shape."""
    import io

    from matplotlib.figure import Figure
    from PIL import Image as PILImage

    from slamkit.viz.scene import VIEWER_FOV_DEG
    from slamkit.viz.static_twin import _project, draw_map_from_camera, map_picture

    view = run["view"]
    view.reset_camera()
    p = np.asarray(view._out.camera_position, float)
    forward = -p / np.linalg.norm(p)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    ndc, depth = _project(np.array([[0.0, 0, 0], 0.5 * right, 0.5 * up]), p, view.aspect)
    t = np.tan(np.radians(VIEWER_FOV_DEG) / 2)
    assert np.allclose(ndc[0], 0) and np.allclose(depth, np.linalg.norm(p))
    assert ndc[1] == pytest.approx([0.5 / (np.linalg.norm(p) * t * view.aspect), 0], abs=1e-9)
    assert ndc[2] == pytest.approx([0, 0.5 / (np.linalg.norm(p) * t)], abs=1e-9)
    drawn = draw_map_from_camera(Figure().add_subplot(), view)
    assert drawn["keyframes"] == len(view.keyframe_ids) and drawn["path"] >= 2 and drawn["current"] == 1
    assert 0.9 * view.num_points <= drawn["points"] <= view.num_points
    img = PILImage.open(io.BytesIO(map_picture(view, 300)))
    assert img.size == (round(300 * view.aspect), 300 + 44)
    rgb = np.asarray(img.convert("RGB"), np.int16)
    assert ((rgb.max(axis=2) - rgb.min(axis=2)) > 40).mean() > 0.01  # coloured points and cameras drawn
    empty = MapView(vis=run["view"].vis, name="empty-picture")
    assert draw_map_from_camera(Figure().add_subplot(), empty) == dict.fromkeys(drawn, 0)  # "no map yet"


def test_step_explanation_counts_nest(run):
    """describe_step's counts read as subsets: pose inliers of the local-map matches, the tracked matches (to the
    last keyframe) of those inliers; the numbers are the result's own (the explanation once printed "916 tracked
    matches, 1172 pose inliers" as if the inliers were among the tracked matches)."""
    results = run["tracked"]
    assert len(results) >= 10
    pattern = re.compile(r"(\d+) pose inliers of (\d+) local-map matches, (\d+) of them tracked from the last keyframe")
    more_inliers = 0
    for r in results:
        m = pattern.search(describe_step(r))
        assert m, describe_step(r)
        inliers, matches, tracked = (int(v) for v in m.groups())
        assert (inliers, tracked) == (r.inliers, r.matches) and matches == len(r.tracked)
        assert tracked <= inliers <= matches
        assert int(r.tracked.inliers.sum()) == r.inliers  # the local-map matches' inlier mask is the pose's
        more_inliers += r.inliers > r.matches
    assert more_inliers > 0  # the case the old wording got wrong occurs on this run


def test_step_html_names_the_thresholds(run):
    slam = run["slam"]
    r = next(r for r in [slam.last_result] if r is not None)
    text = fv.step_html(r, slam.config)
    assert f"frame <b>{r.frame_index}</b>" in text
    summary = fv.summary_numbers(slam)
    assert summary["keyframes"] == slam.slam_map.num_keyframes and summary["frames"] == len(slam.records)
    assert 0 < summary["reprojection_error_px"] < 4
    assert 'class="points">%d<' % slam.slam_map.num_points in fv.summary_html(summary)
    top = max(slam.timings, key=slam.timings.get)  # the costliest stage so far leads the stage line
    assert summary["stages"].startswith(f"{top} {1e3 * slam.timings[top] / len(slam.records):.0f}")
    assert summary["stages"] in fv.summary_html(summary)


# ---------------------------------------------------------------------------------------------- the app


def test_app_controls_pending_reset_and_background_run(run, tmp_path):
    from slamkit.viz.app import SlamApp

    app = SlamApp("default", SlamConfig().with_overrides(frame_skip=2, init_frames=10, max_frames=24,
                                                         num_features=1000),
                  out_dir=tmp_path / "out", view=MapView(server=run["view"].server, name="app"))
    try:
        assert app.w_max.max == 180 and app.w_max.value == 24  # 360 frames / skip 2
        app.w_skip.value = 3
        assert app.w_max.max == 120
        app.w_skip.value = 2
        for _ in range(12):
            app.step()
        assert app.result.status in ("initialized", "tracked")
        # a slider changed mid-run does not touch the running config, and the UI says so
        app.w_flow.value = 0.1
        assert app.slam.config.keyframes.flow_threshold == 0.05
        assert app.pending_changes() == {"flow_threshold": (0.05, 0.1)}
        assert "takes effect on Reset" in app.w_pending.value
        app.step()
        assert app.slam.config.keyframes.flow_threshold == 0.05

        async def run_then_pause():
            app.start()
            assert app.running and app.b_run.description == "Pause" and app.b_step.disabled
            for _ in range(400):
                await asyncio.sleep(0)
                if len(app.slam.records) >= 16:
                    break
            app.pause()
            await asyncio.sleep(0)
            await app._task
            return len(app.slam.records)

        n = asyncio.run(run_then_pause())
        assert 16 <= n < 24 and not app.running and app.b_run.description == "Run"
        app.reset()
        assert app.slam.config.keyframes.flow_threshold == 0.1
        assert len(app.slam.records) == 0 and app.pending_changes() == {} and app.w_pending.value == ""
        assert app.view.scene_counts()["points"] == 0
        app.run()
        assert app.slam.done and app.slam.finished
        assert app.view.scene_counts()["points"] == app.slam.slam_map.num_points
        assert app.view.scene_counts()["keyframes"] == app.slam.slam_map.num_keyframes
        assert app.f_cur.value[:2] == b"\xff\xd8" and app.f_kf.value[:2] == b"\xff\xd8"
        assert "keyframe image id" in app.f_kf_label.value
        assert app.step() is None and "the run is finished" in app.status_text  # Step at the end says so
        # the static twin (what a notebook saved without widget state shows): a picture and the status
        from slamkit.viz.static_twin import app_picture, app_text
        assert app_picture(app)[:8] == b"\x89PNG\r\n\x1a\n"
        twin = app_text(app)
        assert twin.startswith("status: the run is finished") and (
            f"frames 24 of 24 · keyframes {app.slam.slam_map.num_keyframes} · points {app.slam.slam_map.num_points}"
            in twin), twin
        # the finished map is also frozen in the app's view: a saved notebook shows it without a kernel
        assert 'class="slamkit-snapshot"' in app.map_html.value and "slamkit-legend" in app.v_legend.value
        # the legend lists what is drawn: no track or loop closure here, points by height
        assert "points by height" in app.v_legend.value and "loop closure" not in app.v_legend.value
        assert "selected track" not in app.v_legend.value
        assert app.m_image.layout.display == "none"  # no broken-image icon before a picture is drawn
        kfs = sorted(app.slam.slam_map.keyframes)
        assert (app.m_kf1.value, app.m_kf2.value) == (kfs[-2], kfs[-1])  # the latest two keyframes
        final = np.linalg.inv(app.slam.pose_of(len(app.slam.records) - 1))  # after the final global BA
        assert np.allclose(app.view._map.current, final)
        assert "<b>50 px</b> here (f = 500 px)" in app.w_help.value and "map units" in app.v_units.value
        img = app.draw_keyframe_matches()
        assert img is not None and "observe the same 3D points" in app.m_label.value
        assert app.m_image.layout.display is None
        # the track choices: the longest tracks of the map, longest first
        longest = [p for _, p in app.v_track.options[1:]]
        lengths = [app.slam.slam_map.reconstruction.point3D(p).track.length() for p in longest]
        assert lengths == sorted(lengths, reverse=True) and lengths[0] == max(
            app.slam.slam_map.reconstruction.point3D(p).track.length() for p in app.view.point_ids())
        app.v_track.value = longest[0]
        assert app.view.scene_counts()["track"] >= 2 and "keyframes that see it" in app.v_track_info.value
        app.v_clip_on.value = True
        assert app.view.settings.clip is not None
        saved = app.save()
        assert (saved / "trajectory_tum.txt").is_file() and (saved / "sparse").is_dir()
        app.load()
        assert "showing the saved run" in app.w_status.value and "<" not in app.status_text
        page = app.export_html().read_text()
        assert "<title>slamkit map: " in page and "MeshCat</title>" not in page and "slamkit-caption" in page
        # Save again: the map.html just exported into the run folder survives it (byte for byte), and a
        # folder holding a file that is not a run's is refused with the reason, nothing deleted
        first_id = json.loads((saved / ".slamkit-run").read_text())["id"]
        assert app.save() == saved and (saved / "map.html").read_text() == page
        assert json.loads((saved / ".slamkit-run").read_text())["id"] != first_id  # a new save, not a no-op
        assert "kept map.html" in app.status_text and not list(saved.parent.glob(".out.kept-*"))
        (saved / "notes.txt").write_text("mine")
        app.b_save.click()
        assert "also holds what slamkit did not write (notes.txt)" in app.status_text, app.status_text
        assert (saved / "notes.txt").read_text() == "mine" and (saved / "map.html").read_text() == page
        (saved / "notes.txt").unlink()
        # Export dataset: every posed frame of the main segment, its image beside the model
        ds = app.export_dataset("colmap")
        rec = pycolmap.Reconstruction(str(ds / "sparse" / "0"))
        assert rec.num_reg_images() == len(app.slam.trajectory()) and "dataset written" in app.status_text
        assert all((ds / "images" / rec.image(i).name).is_file() for i in rec.reg_image_ids())
        # Reset forgets the discarded run's picture, clip range and track
        app.reset()
        assert app.m_image.value == b"" and app.m_label.value == "" and app.m_image.layout.display == "none"
        assert "slamkit-snapshot" not in app.map_html.value  # the discarded run's frozen map is gone
        app.step()
        assert app.status_text.startswith("stepped to frame 0") and "initializing: no map yet" in app.f_kf_label.value
        assert not app.v_clip_on.value and app.view.settings.clip is None and app.v_track.value == -1
        assert app.view.settings.track_point == -1 and list(app.m_kf1.options) == []
        # an unknown data source is reported, not raised
        app.w_source.value = str(tmp_path / "missing")
        assert "does not exist" in app.w_status.value
    finally:
        app.close()
