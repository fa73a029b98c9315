#!/usr/bin/env python3
"""Download and unpack the public benchmark sequences slamkit is evaluated on (needs internet).

    python data_scripts/download_datasets.py --list
    python data_scripts/download_datasets.py tum_fr1_xyz tum_fr1_desk --dest data/
    python data_scripts/download_datasets.py kitti_odometry_gray --dest data/   # 22 GB

Pure standard library (urllib). Every file goes to ``DEST/.downloads/NAME.part`` first; an interrupted
download resumes where it stopped (HTTP Range; a server that ignores Range is read again from the start),
the finished file is checked against the size the server announced and against the size / SHA-256 in the
table below when they are known, and only then renamed into place and unpacked (``DEST/<folder>/``, zip and
tar archives, no paths outside ``DEST``). A rerun skips what is already downloaded and unpacked. Without a
connection the script says so and what to download by hand.

``--base-url URL`` replaces the host part of every URL (a mirror, or the tests' local server): the file is
fetched from ``URL/<path>`` with the same ``<path>`` as in :data:`FILES`.

Exit status: 0 done, 2 bad arguments, 3 offline / server unreachable, 4 a download failed verification.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import socket
import sys
import tarfile
import urllib.error
import urllib.request
import zipfile
from dataclasses import dataclass
from pathlib import Path

BASES = {
    "tum": "https://cvg.cit.tum.de/rgbd/dataset",
    "kitti": "https://s3.eu-central-1.amazonaws.com/avg-kitti",
    # the ETH ASL server of EuRoC; if it has moved, pass --base-url with the new host (same paths)
    "euroc": "http://robotics.ethz.ch/~asl-datasets/ijrr_euroc_mav_dataset",
}


@dataclass(frozen=True)
class Remote:
    """One file to fetch: ``BASES[base] + "/" + path``; ``size`` bytes and ``sha256`` when published
    (None: checked against the server's Content-Length only)."""

    base: str
    path: str
    size: int | None = None
    sha256: str | None = None

    @property
    def filename(self) -> str:
        return self.path.rsplit("/", 1)[-1]


# name -> (files, what it is). The one table of URLs; sizes/checksums are not published for these archives,
# so they are verified against the server's announced length and the archive's own integrity (CRC for zip,
# a full read for tar).
DATASETS: dict[str, tuple[tuple[Remote, ...], str]] = {
    "tum_fr1_xyz": ((Remote("tum", "freiburg1/rgbd_dataset_freiburg1_xyz.tgz"),), "TUM RGB-D fr1/xyz (0.5 GB)"),
    "tum_fr2_xyz": ((Remote("tum", "freiburg2/rgbd_dataset_freiburg2_xyz.tgz"),), "TUM RGB-D fr2/xyz (2.4 GB)"),
    "tum_fr1_desk": ((Remote("tum", "freiburg1/rgbd_dataset_freiburg1_desk.tgz"),), "TUM RGB-D fr1/desk (0.4 GB)"),
    "tum_fr3_long_office_household": (
        (Remote("tum", "freiburg3/rgbd_dataset_freiburg3_long_office_household.tgz"),),
        "TUM RGB-D fr3/long_office_household (1.6 GB)"),
    "kitti_odometry_gray": ((Remote("kitti", "data_odometry_gray.zip"), Remote("kitti", "data_odometry_calib.zip"),
                             Remote("kitti", "data_odometry_poses.zip")),
                            "KITTI odometry, grey images of sequences 00-21 + calibration + poses of 00-10 (22 GB)"),
    "kitti_odometry_poses": ((Remote("kitti", "data_odometry_poses.zip"), Remote("kitti", "data_odometry_calib.zip")),
                             "KITTI odometry calibration + ground-truth poses only (small)"),
    "euroc_mh_01_easy": ((Remote("euroc", "machine_hall/MH_01_easy/MH_01_easy.zip"),), "EuRoC MAV MH_01_easy (ASL)"),
    "euroc_v1_01_easy": ((Remote("euroc", "vicon_room1/V1_01_easy/V1_01_easy.zip"),), "EuRoC MAV V1_01_easy (ASL)"),
}

CHUNK = 1 << 20


class DownloadError(Exception):
    """A download could not be completed or verified (message says which file and why)."""


class OfflineError(DownloadError):
    """The server could not be reached at all."""


def url_of(remote: Remote, base_url: str | None = None) -> str:
    return f"{(base_url or BASES[remote.base]).rstrip('/')}/{remote.path}"


def _open(url: str, start: int, timeout: float):
    req = urllib.request.Request(url, headers={"User-Agent": "slamkit-data-scripts/1"})
    if start:
        req.add_header("Range", f"bytes={start}-")
    try:
        return urllib.request.urlopen(req, timeout=timeout)
    except urllib.error.HTTPError as e:
        if e.code == 416 and start:  # range past the end: the partial file is complete (or bad)
            return e
        raise DownloadError(f"{url}: HTTP {e.code} {e.reason}") from None
    except (urllib.error.URLError, socket.timeout, ConnectionError) as e:
        reason = getattr(e, "reason", e)
        raise OfflineError(f"cannot reach {url} ({reason}); are you offline? The datasets need an internet "
                           "connection (or a mirror: --base-url)") from None


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def download(url: str, target: Path, size: int | None = None, sha256: str | None = None, *,
             timeout: float = 30.0, log=print) -> Path:
    """Fetch ``url`` into ``target`` (resuming ``target.part``), verify, rename into place; returns target.
    A ``target`` already there with the right size (and checksum) is kept."""
    target = Path(target)
    if target.exists() and (size is None or target.stat().st_size == size) and (
            sha256 is None or sha256_of(target) == sha256):
        log(f"{target.name}: already downloaded")
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    part = target.with_name(target.name + ".part")
    start = part.stat().st_size if part.exists() else 0
    resp = _open(url, start, timeout)
    total = None
    with resp:
        status = getattr(resp, "status", None) or resp.getcode()
        if status == 416:
            total, mode = start, None  # nothing left to read
        elif status == 206:
            content_range = resp.headers.get("Content-Range", "")
            if not content_range.startswith(f"bytes {start}-"):
                raise DownloadError(f"{url}: server answered Range {start}- with {content_range!r}")
            total = int(content_range.rsplit("/", 1)[1]) if not content_range.endswith("/*") else None
            mode = "ab"
            log(f"{target.name}: resuming at {start} bytes")
        else:
            if start:
                log(f"{target.name}: server ignores Range; downloading again from the start")
            start, mode = 0, "wb"
            length = resp.headers.get("Content-Length")
            total = int(length) if length is not None else None
        if mode is not None:
            with open(part, mode) as f:
                while True:
                    block = resp.read(CHUNK)
                    if not block:
                        break
                    f.write(block)
                f.flush()
                os.fsync(f.fileno())
    got = part.stat().st_size
    if total is not None and got != total:
        raise DownloadError(f"{url}: got {got} of {total} bytes (connection dropped?); run again to resume")
    if size is not None and got != size:
        part.unlink()
        raise DownloadError(f"{url}: {got} bytes, expected {size}; the partial file was removed, run again")
    if sha256 is not None:
        digest = sha256_of(part)
        if digest != sha256:
            part.unlink()
            raise DownloadError(f"{url}: SHA-256 {digest} does not match the expected {sha256}; removed, run again")
    os.replace(part, target)
    log(f"{target.name}: {got} bytes" + (" (SHA-256 ok)" if sha256 else ""))
    return target


def _safe_members(names, dest: Path) -> None:
    root = dest.resolve()
    for name in names:
        p = (dest / name).resolve()
        if p != root and root not in p.parents:
            raise DownloadError(f"archive member {name!r} would be written outside {dest}")


def unpack(archive: Path, dest: Path, log=print) -> Path:
    """Unpack a zip / tar(.gz) ``archive`` into ``dest`` once (a ``.unpacked`` marker records it)."""
    marker = dest / ".downloads" / (archive.name + ".unpacked")
    if marker.exists():
        log(f"{archive.name}: already unpacked")
        return dest
    dest.mkdir(parents=True, exist_ok=True)
    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as z:
                bad = z.testzip()
                if bad is not None:
                    raise DownloadError(f"{archive}: member {bad} fails its CRC check (corrupt download)")
                _safe_members(z.namelist(), dest)
                z.extractall(dest)
        elif tarfile.is_tarfile(archive):
            with tarfile.open(archive) as t:
                members = t.getmembers()
                _safe_members([m.name for m in members], dest)
                try:
                    t.extractall(dest, filter="data")
                except TypeError:  # Python without extraction filters
                    t.extractall(dest)
        else:
            raise DownloadError(f"{archive}: neither a zip nor a tar archive")
    except (zipfile.BadZipFile, tarfile.TarError, EOFError, OSError) as e:
        raise DownloadError(f"{archive}: cannot unpack ({e}); delete it and run again") from None
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text("ok\n")
    log(f"{archive.name}: unpacked into {dest}")
    return dest


def fetch_dataset(name: str, dest: Path, base_url: str | None = None, keep_archives: bool = True,
                  log=print) -> Path:
    """Download and unpack every file of ``DATASETS[name]`` under ``dest``."""
    if name not in DATASETS:
        raise KeyError(name)
    files, _ = DATASETS[name]
    for remote in files:
        archive = download(url_of(remote, base_url), dest / ".downloads" / remote.filename, remote.size,
                           remote.sha256, log=log)
        unpack(archive, dest, log=log)
        if not keep_archives:
            archive.unlink()
    return dest


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("datasets", nargs="*", help="names from --list (or 'all_tum')")
    p.add_argument("--dest", default="data", help="folder to unpack into (default ./data)")
    p.add_argument("--base-url", help="fetch every file from this host instead (same paths)")
    p.add_argument("--list", action="store_true", help="list the datasets and their URLs")
    p.add_argument("--delete-archives", action="store_true", help="remove each archive after unpacking")
    args = p.parse_args(argv)
    if args.list or not args.datasets:
        for name, (files, what) in DATASETS.items():
            print(f"{name:32s} {what}")
            for r in files:
                print(f"{'':32s}   {url_of(r, args.base_url)}")
        return 0 if args.list else 2
    names = []
    for n in args.datasets:
        names += [k for k in DATASETS if k.startswith("tum_")] if n == "all_tum" else [n]
    unknown = [n for n in names if n not in DATASETS]
    if unknown:
        print(f"unknown dataset(s): {', '.join(unknown)}; known: {', '.join(DATASETS)}", file=sys.stderr)
        return 2
    dest = Path(args.dest)
    for name in names:
        try:
            fetch_dataset(name, dest, args.base_url, keep_archives=not args.delete_archives)
        except OfflineError as e:
            urls = " ".join(url_of(r, args.base_url) for r in DATASETS[name][0])
            print(f"error: {e}\n  to install by hand, download {urls} into {dest / '.downloads'}/ and run this "
                  "again (it verifies and unpacks what is there)", file=sys.stderr)
            return 3
        except DownloadError as e:
            print(f"error: {name}: {e}", file=sys.stderr)
            return 4
    print(f"done: {', '.join(names)} in {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
