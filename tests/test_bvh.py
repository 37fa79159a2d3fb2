import re
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from avatar_motor.data.cache import MotionCache, default_cache_dir, import_motion
from avatar_motor.io.bvh import BVHError, parse_bvh, read_bvh, write_bvh

FIX = Path(__file__).parent / "fixtures"

SMALL = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Chest
  {
    OFFSET 0 10 0
    CHANNELS 6 Xposition Yposition Zposition Yrotation Xrotation Zrotation
    End Site
    {
      OFFSET 0 5 0
    }
  }
  JOINT Leg
  {
    OFFSET 0 -10 0
    CHANNELS 2 Xrotation Zrotation
    End Site
    {
      OFFSET 0 -9 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.008333
1 2 3 10 20 30 0 10 0 5 6 7 45 -45
1.5 2 3 11 21 31 0.1 10 0 5 6 7 40 -40
"""


def test_roundtrip_any_channels(tmp_path):
    b = parse_bvh(SMALL, "small.bvh")
    assert b.names == ["Hips", "Chest", "Leg"] and b.parents == [-1, 0, 0]
    assert abs(b.fps - 120) < 0.1 and b.channels[2] == ["Xrotation", "Zrotation"]
    assert np.allclose(b.local_translations()[1, 1], [0.1, 10, 0])  # position channels on a child
    write_bvh(tmp_path / "a.bvh", b)
    b2 = read_bvh(tmp_path / "a.bvh")
    assert np.allclose(b2.motion, b.motion, atol=1e-5) and np.allclose(b2.offsets, b.offsets, atol=1e-5)
    assert b2.channels == b.channels and b2.names == b.names
    assert np.allclose(b2.end_sites[1], [0, 5, 0])
    P1, G1 = b.global_transforms()
    P2, G2 = b2.global_transforms()
    assert np.allclose(P1, P2, atol=1e-5) and np.allclose(G1, G2, atol=1e-5)


@pytest.mark.parametrize("name", ["walk_lafan1", "walk_cmu", "walk_mixamo"])
def test_roundtrip_fixtures(tmp_path, name):
    b = read_bvh(FIX / f"{name}.bvh")
    write_bvh(tmp_path / "x.bvh", b)
    b2 = read_bvh(tmp_path / "x.bvh")
    assert np.allclose(b.motion, b2.motion, atol=1e-5)
    assert np.allclose(b.global_transforms()[0], b2.global_transforms()[0], atol=1e-4)


def _mutations():
    good = SMALL
    head, motion = good.split("MOTION")
    return {
        "truncated motion": (good.rsplit("\n", 2)[0] + "\n", "truncated"),
        "wrong channel count": (good.replace("5 6 7 45 -45", "5 6 7 45"), "channel count|rows differ"),
        "non-numeric": (good.replace("45 -45", "45 abc"), "not numeric"),
        "zero frames": (good.replace("Frames: 2", "Frames: 0"), "0 frames"),
        "absurd frame time": (good.replace("0.008333", "1000"), "frame time"),
        "empty hierarchy": ("HIERARCHY\nMOTION\nFrames: 1\nFrame Time: 0.03\n\n", "no joints"),
        "cyclic hierarchy": (good.replace("JOINT Leg", "JOINT Hips"), "appears twice"),
        "unclosed braces": (head.rsplit("}", 1)[0] + "MOTION" + motion, "not closed"),
        "no MOTION": (head, "no MOTION"),
        "bad offset": (good.replace("OFFSET 0 10 0", "OFFSET 0 ten 0"), "must be a number"),
        "unknown channel": (good.replace("Xrotation Zrotation", "Xrotation Wrotation"), "unknown channel"),
        "NaN values": (good.replace("45 -45", "45 nan"), "NaN"),
    }


@pytest.mark.parametrize("kind", list(_mutations()))
def test_malformed_bvh_errors_name_file_and_problem(tmp_path, kind):
    text, pattern = _mutations()[kind]
    p = tmp_path / f"bad_{kind.replace(' ', '_')}.bvh"
    p.write_text(text)
    with pytest.raises(BVHError, match=pattern) as e:
        read_bvh(p)
    assert str(p) in str(e.value)


def test_binary_garbage_and_missing_file(tmp_path):
    p = tmp_path / "garbage.bvh"
    p.write_bytes(bytes(range(256)) * 10)
    with pytest.raises(BVHError, match="binary") as e:
        read_bvh(p)
    assert "garbage.bvh" in str(e.value)
    with pytest.raises(BVHError, match="cannot be opened"):
        read_bvh(tmp_path / "missing.bvh")


def test_unknown_skeleton_needs_mapping(tmp_path):
    from avatar_motor.data.retarget import retarget
    with pytest.raises(BVHError, match="unknown skeleton.*mapping"):
        retarget(parse_bvh(SMALL, "small.bvh"))


def test_import_skips_bad_files_with_reasons_and_never_half_writes(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for n in ("walk_lafan1", "walk_cmu"):
        (src / f"{n}.bvh").write_bytes((FIX / f"{n}.bvh").read_bytes())
    (src / "broken.bvh").write_text(_mutations()["truncated motion"][0])
    (src / "odd.bvh").write_text(SMALL)
    path, s = import_motion(src, progress=False)
    assert s["clips"] == 2 and len(s["skipped"]) == 2
    reasons = " ".join(x["reason"] for x in s["skipped"])
    assert "broken.bvh" in reasons and "truncated" in reasons and "unknown skeleton" in reasons
    before = path.read_bytes()
    # an import that fails completely leaves the existing cache untouched and no temp files
    empty = tmp_path / "nothing"
    empty.mkdir()
    (empty / "broken.bvh").write_text("garbage")
    with pytest.raises(FileExistsError, match="--replace"):  # another source under the same name
        import_motion(empty, name=path.stem, progress=False)
    with pytest.raises(ValueError, match="no clip could be imported"):
        import_motion(empty, name=path.stem, progress=False, replace=True)
    assert path.read_bytes() == before
    assert not [p for p in path.parent.iterdir() if ".tmp" in p.name]


def test_import_archives_and_incremental(tmp_path):
    src = tmp_path / "d"
    src.mkdir()
    for n in ("walk_lafan1", "walk_cmu", "walk_mixamo"):
        (src / f"{n}.bvh").write_bytes((FIX / f"{n}.bvh").read_bytes())
    tar = tmp_path / "clips.tar.xz"
    with tarfile.open(tar, "w:xz") as tf:
        tf.add(src, arcname="clips")
    zp = tmp_path / "clips.zip"
    with zipfile.ZipFile(zp, "w") as zf:
        for f in src.iterdir():
            zf.write(f, f"z/{f.name}")
    _, s_tar = import_motion(tar, progress=False, workers=1)
    _, s_zip = import_motion(zp, name="zipped", progress=False, workers=1)
    assert s_tar["clips"] == 3 and s_zip["clips"] == 3
    path, s1 = import_motion(src, progress=False, workers=1)
    _, s2 = import_motion(src, progress=False, workers=1)
    assert s1["new"] == 3 and s2["new"] == 0 and s2["unchanged"] == 3
    c = MotionCache.load(path)
    assert c.root_pos.shape[0] == c.clip_len.sum() == c.quats.shape[0]
    assert all(x["info"]["skeleton"] in ("lafan1", "cmu", "mixamo") for x in c.clips)
    assert path.parent == default_cache_dir()


def test_corrupt_cache_gives_clear_error(tmp_path):
    p = tmp_path / "bad.npz"
    p.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable motion cache.*import"):
        MotionCache.load(p)


def test_cache_of_an_older_importer_is_named_and_converted_anew(tmp_path):
    src = tmp_path / "d"
    src.mkdir()
    (src / "walk_cmu.bvh").write_bytes((FIX / "walk_cmu.bvh").read_bytes())
    path, _ = import_motion(src, progress=False, workers=1)
    c = MotionCache.load(path)
    c.meta["version"] -= 1  # as an earlier importer wrote it
    c.save(path)
    with pytest.raises(ValueError, match="older importer.*data import"):
        MotionCache.load(path)
    _, s = import_motion(src, progress=False, workers=1)
    assert s["new"] == 1 and s["unchanged"] == 0
    assert MotionCache.load(path).meta["version"] == c.meta["version"] + 1


def _run_import(args: list[str], env_cache: Path) -> subprocess.Popen:
    import os
    # the peak is VmHWM of the importing process (getrusage's maxrss would carry over the parent
    # pytest's own peak through fork and exec); its workers, started only for accepted members,
    # are not counted
    return subprocess.Popen([sys.executable, "-c", "import re, sys\nfrom avatar_motor.cli import main\n"
                             "rc = main(sys.argv[1:])\n"
                             "hwm = re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read())[1]\n"
                             "print('peak_kb', hwm, flush=True)\nsys.exit(rc)", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "AVATAR_MOTOR_CACHE": str(env_cache)})


def test_an_archive_bomb_fails_clearly_within_bounded_memory(tmp_path):
    """1 GB of zeros in a 1 MB zip once peaked at 4.7 GB; 100 MB of newlines after a valid clip
    was parsed at 3.4 GB. Members are size-checked before reading and BVH motion is read lazily."""
    import zipfile
    bomb = tmp_path / "bomb.zip"
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zf, zf.open("big.bvh", "w", force_zip64=True) as f:
        chunk = bytes(1 << 24)
        for _ in range(64):  # 1 GiB
            f.write(chunk)
    assert bomb.stat().st_size < 2 << 20
    p = _run_import(["data", "import", str(bomb), "--workers", "2"], tmp_path / "c")
    out, err = p.communicate(timeout=300)
    assert p.returncode == 2 and "larger than 256 MB" in err and "Split the capture" in err, err
    peak_mb = int(out.split()[-1]) / 1024
    print(f"archive bomb: refused, peak {peak_mb:.0f} MB")
    assert peak_mb < 1024
    # a valid clip followed by 100 MB of blank lines: nothing past the last frame is read
    clip = (Path(__file__).parent / "fixtures" / "walk_lafan1.bvh").read_bytes()
    padded = tmp_path / "padded"
    padded.mkdir()
    with open(padded / "walk.bvh", "wb") as f:
        f.write(clip + b"\n" * (100 << 20))
    p = _run_import(["data", "import", str(padded), "--workers", "1"], tmp_path / "c")
    out, err = p.communicate(timeout=300)
    peak_mb = int(out.split()[-1]) / 1024
    print(f"100 MB of newlines after a clip: imported, peak {peak_mb:.0f} MB")
    assert p.returncode == 0 and "1 clips" in out and peak_mb < 1024, (out, err)
    assert b"\x00" not in clip
    with pytest.raises(BVHError, match="more than"):  # a declared size beyond the limit, before allocating
        parse_bvh(re.sub(r"Frames:\s*\d+", "Frames: 999999999", clip.decode()))


def test_killing_an_import_leaves_no_worker_behind(tmp_path):
    import os
    import signal
    import time
    src = tmp_path / "many"
    src.mkdir()
    clip = (Path(__file__).parent / "fixtures" / "walk_lafan1.bvh").read_bytes()
    for k in range(400):
        (src / f"c{k:03d}.bvh").write_bytes(clip)
    p = _run_import(["data", "import", str(src), "--workers", "2"], tmp_path / "c")
    children = []
    end = time.time() + 60
    while time.time() < end and len(children) < 2:
        time.sleep(0.2)
        children = [int(c) for c in Path(f"/proc/{p.pid}/task/{p.pid}/children").read_text().split()]
    assert len(children) >= 2, "the import did not start its workers"
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    end = time.time() + 10
    while time.time() < end and any(Path(f"/proc/{c}").exists() and "Z" not in Path(f"/proc/{c}/stat").read_text().split(")")[1][:3]
                                    for c in children):
        time.sleep(0.2)
    alive = [c for c in children if Path(f"/proc/{c}").exists() and "Z" not in Path(f"/proc/{c}/stat").read_text().split(")")[1][:3]]
    assert not alive, f"workers {alive} outlived the killed import"


def test_any_line_ending_reads_the_same():
    text = (Path(__file__).parent / "fixtures" / "walk_lafan1.bvh").read_text()
    ref = parse_bvh(text)
    for eol in ("\r\n", "\r"):
        b = parse_bvh(text.replace("\n", eol))
        assert b.names == ref.names and np.array_equal(b.motion, ref.motion)
