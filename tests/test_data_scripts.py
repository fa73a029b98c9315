"""data_scripts/: downloads from a local HTTP server (never the internet) serving small archives made here —
unpacking, resume with HTTP Range, a server that ignores Range, size/checksum verification, the offline
message — and frame extraction from a small generated video."""

from __future__ import annotations

import hashlib
import importlib.util
import io
import subprocess
import sys
import tarfile
import threading
import zipfile
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "data_scripts"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses need the module registered
    spec.loader.exec_module(mod)
    return mod


dl = _load("download_datasets")
ex = _load("extract_frames")


class RangeHandler(SimpleHTTPRequestHandler):
    """Static files with ``Range: bytes=N-`` support (http.server has none); records the requests."""

    log: list = []
    honour_range = True

    def log_message(self, *a):  # quiet
        pass

    def do_GET(self):
        path = Path(self.translate_path(self.path))
        type(self).log.append((self.path, self.headers.get("Range")))
        if not path.is_file():
            self.send_error(404)
            return
        data = path.read_bytes()
        rng = self.headers.get("Range")
        if rng and self.honour_range:
            start = int(rng.split("=")[1].rstrip("-"))
            if start >= len(data):
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(data)}")
                self.end_headers()
                return
            body = data[start:]
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        else:
            body = data
            self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)


@pytest.fixture
def server(tmp_path):
    root = tmp_path / "www"
    root.mkdir()
    handler = type("H", (RangeHandler,), {"log": [], "honour_range": True})

    def factory(*a, **kw):
        return handler(*a, directory=str(root), **kw)

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), factory)
    th = threading.Thread(target=httpd.serve_forever, daemon=True)
    th.start()
    yield root, f"http://127.0.0.1:{httpd.server_address[1]}", handler
    httpd.shutdown()
    httpd.server_close()


def _tum_tgz(name: str) -> bytes:
    """A tiny TUM-layout archive: rgb.txt, groundtruth.txt and a few 'images' (random bytes, incompressible)."""
    buf = io.BytesIO()
    rng = np.random.default_rng(0)
    with tarfile.open(fileobj=buf, mode="w:gz") as t:
        def add(path, data):
            info = tarfile.TarInfo(f"{name}/{path}")
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
        add("rgb.txt", b"# timestamp filename\n1.0 rgb/1.0.png\n2.0 rgb/2.0.png\n")
        add("groundtruth.txt", b"# timestamp tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n")
        for i in (1, 2):
            add(f"rgb/{i}.0.png", rng.bytes(60_000))
    return buf.getvalue()


def _publish(root: Path, remote, data: bytes) -> Path:
    path = root / remote.path
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def test_dataset_table_is_complete():
    names = set(dl.DATASETS)
    for n in ("tum_fr1_xyz", "tum_fr2_xyz", "tum_fr1_desk", "tum_fr3_long_office_household",
              "kitti_odometry_gray", "euroc_mh_01_easy"):
        assert n in names
    for files, what in dl.DATASETS.values():
        assert what and files and all(r.base in dl.BASES for r in files)
        assert all(dl.url_of(r).startswith(("https://", "http://")) for r in files)


def test_tum_download_unpack_and_rerun(server, tmp_path, capsys):
    root, base, handler = server
    remote = dl.DATASETS["tum_fr1_xyz"][0][0]
    _publish(root, remote, _tum_tgz("rgbd_dataset_freiburg1_xyz"))
    dest = tmp_path / "data"
    assert dl.main(["tum_fr1_xyz", "--dest", str(dest), "--base-url", base]) == 0
    seq = dest / "rgbd_dataset_freiburg1_xyz"
    assert (seq / "rgb.txt").read_text().startswith("# timestamp") and len(list((seq / "rgb").glob("*.png"))) == 2
    assert not list(dest.rglob("*.part"))
    n = len(handler.log)
    assert dl.main(["tum_fr1_xyz", "--dest", str(dest), "--base-url", base]) == 0  # nothing to do again
    assert len(handler.log) == n and "already downloaded" in capsys.readouterr().out


def test_resume_with_range(server, tmp_path):
    root, base, handler = server
    data = _tum_tgz("x")
    remote = dl.Remote("tum", "freiburg1/x.tgz", size=len(data), sha256=hashlib.sha256(data).hexdigest())
    _publish(root, remote, data)
    target = tmp_path / "dl" / "x.tgz"
    target.parent.mkdir()
    half = len(data) // 2
    Path(str(target) + ".part").write_bytes(data[:half])  # an interrupted earlier download
    dl.download(dl.url_of(remote, base), target, remote.size, remote.sha256, log=lambda *a: None)
    assert target.read_bytes() == data
    assert handler.log[-1][1] == f"bytes={half}-"
    # a server that ignores Range: the file is read again from the start, still correct
    handler.honour_range = False
    target.unlink()
    Path(str(target) + ".part").write_bytes(data[:half])
    dl.download(dl.url_of(remote, base), target, remote.size, remote.sha256, log=lambda *a: None)
    assert target.read_bytes() == data


def test_checksum_and_size_mismatch_are_errors(server, tmp_path):
    root, base, _ = server
    data = b"not what was published" * 100
    bad_sum = dl.Remote("kitti", "a.zip", sha256="0" * 64)
    _publish(root, bad_sum, data)
    target = tmp_path / "a.zip"
    with pytest.raises(dl.DownloadError, match="SHA-256"):
        dl.download(dl.url_of(bad_sum, base), target, None, bad_sum.sha256, log=lambda *a: None)
    assert not target.exists() and not Path(str(target) + ".part").exists()
    with pytest.raises(dl.DownloadError, match="2200 bytes, expected 5;"):
        dl.download(dl.url_of(bad_sum, base), target, 5, None, log=lambda *a: None)
    with pytest.raises(dl.DownloadError, match="HTTP 404"):
        dl.download(f"{base}/missing.zip", target, log=lambda *a: None)


def test_kitti_zip_unpacks_and_rejects_corrupt(server, tmp_path):
    root, base, _ = server
    files = dl.DATASETS["kitti_odometry_poses"][0]
    for r in files:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as z:
            z.writestr(f"dataset/{r.filename}.txt", "0 " * 12)
        _publish(root, r, buf.getvalue())
    dest = tmp_path / "kitti"
    dl.fetch_dataset("kitti_odometry_poses", dest, base, log=lambda *a: None)
    assert (dest / "dataset" / "data_odometry_poses.zip.txt").exists()
    evil = tmp_path / "evil.zip"
    with zipfile.ZipFile(evil, "w") as z:
        z.writestr("../outside.txt", "x")
    with pytest.raises(dl.DownloadError, match="outside"):
        dl.unpack(evil, tmp_path / "e", log=lambda *a: None)
    junk = tmp_path / "junk.tgz"
    junk.write_bytes(b"\x1f\x8b" + b"x" * 100)
    with pytest.raises(dl.DownloadError, match="neither a zip nor a tar|cannot unpack"):
        dl.unpack(junk, tmp_path / "j", log=lambda *a: None)


def test_offline_message(tmp_path):
    out = subprocess.run([sys.executable, str(SCRIPTS / "download_datasets.py"), "euroc_mh_01_easy",
                          "--dest", str(tmp_path), "--base-url", "http://127.0.0.1:9"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 3
    assert "cannot reach http://127.0.0.1:9/machine_hall/MH_01_easy/MH_01_easy.zip" in out.stderr
    assert "offline" in out.stderr and "by hand" in out.stderr and "Traceback" not in out.stderr


def test_unknown_dataset_and_list(capsys):
    assert dl.main(["tum_fr9"]) == 2
    assert "unknown dataset" in capsys.readouterr().err
    assert dl.main(["--list"]) == 0
    assert "cvg.cit.tum.de/rgbd/dataset/freiburg1/rgbd_dataset_freiburg1_xyz.tgz" in capsys.readouterr().out


def test_extract_frames(tmp_path):
    cv2 = pytest.importorskip("cv2")
    video = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    assert w.isOpened()
    for i in range(12):
        img = np.full((48, 64, 3), i * 20, np.uint8)
        w.write(img)
    w.release()
    out = tmp_path / "frames"
    assert ex.extract_frames(video, out, every=2, max_frames=5, log=lambda *a: None) == 5
    assert sorted(p.name for p in out.glob("*.png")) == [f"{i:06d}.png" for i in range(5)]
    times = np.loadtxt(out / "times.txt")
    assert times == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8])
    second = cv2.imread(str(out / "000001.png"))
    assert abs(int(second.mean()) - 40) <= 3  # the third frame of the video
    assert ex.main([str(tmp_path / "nope.mp4"), str(out)]) == 2
    (tmp_path / "text.mp4").write_text("not a video")
    assert ex.main([str(tmp_path / "text.mp4"), str(out)]) == 2


def test_extract_frames_from_a_name_that_is_not_utf8(tmp_path):
    """A video and an output folder whose names hold a byte that is not UTF-8 (names from cameras and old
    archives): OpenCV's reader and writer crash on such a name; the frames are read and written all the same."""
    cv2 = pytest.importorskip("cv2")
    import os

    root = os.fsencode(tmp_path)
    plain = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(plain), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for i in range(6):
        w.write(np.full((48, 64, 3), i * 40, np.uint8))
    w.release()
    video = Path(os.fsdecode(root + b"/clip\xfe.avi"))
    os.rename(plain, video)
    out = Path(os.fsdecode(root + b"/frames\xff"))
    assert ex.extract_frames(video, out, log=lambda *a: None) == 6
    third = cv2.imdecode(np.fromfile(out / "000002.png", np.uint8), cv2.IMREAD_COLOR)
    assert abs(int(third.mean()) - 80) <= 3
