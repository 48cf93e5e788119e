"""The product contract at its edges: SIGTERM ends a render like Ctrl-C (no orphaned process, resumable), a malformed
or unreachable --scheduler is one line at once, unreadable images are one line without library noise, and commands
check their inputs and output paths before writing anything.

Commands run in a subprocess where the point is what reaches file descriptor 2 or which processes survive.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ddsgen.cli import Terminated, main
from ddsgen.errors import InputError
from ddsgen.io.manifest import read_manifest
from paused_render import wait_for_pause
from tiny_inputs import tiny_preset_yaml, tiny_scenes_yaml, tree_hashes, written_inputs

ENTRY = "from ddsgen.cli import entry_point; entry_point()"


def run_cli(*argv, timeout: float = 120, cwd=None) -> subprocess.CompletedProcess:
    """``ddsgen ARGV`` in a fresh interpreter; stdout and stderr as text."""
    env = dict(os.environ, DDSGEN_NO_COMPILE="1")
    return subprocess.run([sys.executable, "-c", ENTRY, *map(str, argv)], env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=timeout)  # fmt: skip


def assert_one_error_line(result: subprocess.CompletedProcess, *fragments: str) -> str:
    """Exit 2 and exactly one stderr line, ``ddsgen: error: ...`` holding every fragment; returns the line."""
    assert result.returncode == 2, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("ddsgen: error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """(preset path, scene list path): a 64x48 px Kinect-like sensor and a small scene list."""
    with written_inputs(tmp_path_factory.mktemp("inputs"), tiny_preset_yaml(64, 48),
                        tiny_scenes_yaml(frames=3, clutter=(1, 2))) as paths:  # fmt: skip
        yield paths


# ---------------------------------------------------------------- 1. SIGTERM ends a render like Ctrl-C


def _alive(pid: int) -> bool:
    """The process exists and is not a zombie (a zombie has ended; only its parent has not reaped it yet)."""
    try:
        with open(f"/proc/{pid}/stat") as handle:
            return handle.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False


def _descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (children of children too), from /proc."""
    parents: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc (Linux)")
def test_sigterm_mid_render_ends_every_worker_and_the_run_resumes(inputs, tmp_path):
    """SIGTERM to the CLI while two spawn workers render (it pauses after its 2nd manifest record; the workers may be
    anywhere in the frames they hold): exit 143 with one line, no process of the command survives (workers,
    multiprocessing's resource tracker), and re-running the same command finishes the dataset."""
    preset, scenes = inputs
    out = tmp_path / "out"
    argv = ["ddsgen", "render", preset, "--scenes", scenes, "-n", "400", "--out", out, "--workers", "2", "--quiet",
            "--no-preview"]  # fmt: skip
    env = dict(os.environ, DDSGEN_NO_COMPILE="1")
    err_path, flag = tmp_path / "stderr.txt", tmp_path / "paused"
    with open(err_path, "w") as err:  # a file, not a pipe: orphans holding a pipe open would hang the test
        process = subprocess.Popen([sys.executable, str(Path(__file__).with_name("paused_render.py")), "2", str(flag),
                                    "--", *map(str, argv)], env=env, stdout=subprocess.DEVNULL, stderr=err,
                                   start_new_session=True)  # fmt: skip
    family: set[int] = set()
    try:
        wait_for_pause(flag, process, err_path.read_text)
        family |= _descendants(process.pid)
        assert len(family) >= 3, f"expected 2 workers and the resource tracker, found {family}"
        process.send_signal(signal.SIGTERM)
        returncode = process.wait(timeout=30)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and any(_alive(pid) for pid in family):
            time.sleep(0.05)
        survivors = sorted(pid for pid in family if _alive(pid))
    finally:
        for pid in [process.pid, *family]:  # never leave anything behind, even when the test fails
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        process.wait()
    stderr = err_path.read_text()
    assert survivors == [], f"processes outlived the command: {survivors}"
    assert returncode == 128 + signal.SIGTERM, stderr
    # one line, no empty line before it (click's own Ctrl-C handling prints one), and the way to go on
    assert stderr == "ddsgen: terminated; finished frames are kept, re-run the same command to resume\n", stderr

    from ddsgen.runner import render_dataset

    done = {r["frame"] for r in read_manifest(out / "manifest.jsonl")}
    assert len(done) == 2, f"the manifest holds {len(done)} records at the pause after the 2nd"
    # The same run (seed, preset, scenes), finished a little further: past any frame a worker had written the files
    # of without its record (the resume renders those again and replaces them).
    written = {int(path.stem) for path in (out / "depth").glob("[0-9]*.png")}  # not a temporary (".NNNNNN...")
    n = max(done | written) + 2
    summary = render_dataset(preset, scenes, n, str(out), workers=1, progress=False)
    assert summary.frames_skipped == len(done) and summary.frames_rendered == n - len(done)
    assert [r["frame"] for r in read_manifest(out / "manifest.jsonl")] == list(range(n))
    assert not [p for p in out.rglob(".*") if p.is_file()], "temporary files left behind"
    uninterrupted = tmp_path / "uninterrupted"
    render_dataset(preset, scenes, n, str(uninterrupted), workers=1, progress=False)
    assert tree_hashes(out) == tree_hashes(uninterrupted)


@pytest.mark.parametrize("raised, line, code", [(KeyboardInterrupt, "ddsgen: interrupted", 130),
                                                 (Terminated, "ddsgen: terminated", 143)])
def test_a_stop_while_the_command_line_is_parsed_is_one_line(raised, line, code, monkeypatch, capsys):
    """Ctrl-C or SIGTERM before any command runs (click turns it into Abort and prints an empty line first)."""
    import ddsgen.cli

    def stopped(*args, **kwargs):
        raise raised()

    monkeypatch.setattr(ddsgen.cli.cli, "parse_args", stopped)
    capsys.readouterr()
    assert main(["presets"]) == code
    assert capsys.readouterr().err == line + "\n"


def _slow_batch(job, batch):  # a pool task that is still running when the interrupt comes
    time.sleep(60)
    return batch


def test_an_interrupted_pool_ends_its_manager_thread_before_unwinding():
    """Ctrl-C in a pool: when run_in_pool unwinds, its workers and its manager thread are gone. A manager thread still
    closing its wake-up pipe at interpreter exit raced concurrent.futures' exit hook, which then printed
    "OSError: [Errno 9] Bad file descriptor" after our one line (3 SIGTERMs in 95 on a loaded machine)."""
    import threading

    from ddsgen.worker_pool import run_in_pool

    results = run_in_pool(_slow_batch, None, [[0], [1], [2]], 2, "out")
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # Ctrl-C as Python's own
    timer = threading.Timer(3.0, os.kill, (os.getpid(), signal.SIGINT))  # the workers are busy sleeping by then
    timer.start()
    started = time.monotonic()
    try:
        with pytest.raises(KeyboardInterrupt):
            list(results)
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, previous)
    assert time.monotonic() - started < 30, "the interrupt waited for the tasks"
    managers = [t for t in threading.enumerate() if "ExecutorManager" in type(t).__name__ and t.is_alive()]
    assert managers == []


def test_sigterm_handler_is_restored_after_main(capsys):
    """main() installs its SIGTERM handler for the command only: an embedding program keeps its own behaviour."""
    from ddsgen.cli import main

    before = signal.getsignal(signal.SIGTERM)
    assert main(["presets"]) == 0
    assert signal.getsignal(signal.SIGTERM) == before


# ---------------------------------------------------------------- 2. --scheduler: malformed or unreachable


@pytest.mark.parametrize(
    "address, problem",
    [("notaurl", "no port number"), ("tcp://host", "no port number"), ("http://host:8787", "unknown scheme http://"),
     ("tcp://:8786", "no host name"), ("host:port", "the port is not a number"), ("tcp://host:99999", "out of range")],
)  # fmt: skip
def test_scheduler_address_form_is_checked_before_connecting(address, problem):
    pytest.importorskip("distributed")
    from ddsgen.distributed import check_address

    with pytest.raises(InputError, match=r"^--scheduler: .* is not a scheduler address \(.*tcp://HOST:PORT") as info:
        check_address(address)
    assert problem in str(info.value) and address in str(info.value)
    for good in ("tcp://10.0.0.5:8786", "10.0.0.5:8786", "tls://host:8786", "tcp://[::1]:8786"):
        check_address(good)


def test_malformed_scheduler_is_one_line_at_once(inputs, tmp_path):
    """It was the right line, then 40 s of waiting and a Client.__del__ traceback at exit (how long it takes now:
    bench/bench_edges.py)."""
    pytest.importorskip("distributed")
    preset, scenes = inputs
    result = run_cli("render", preset, "--scenes", scenes, "-n", "2", "--scheduler", "notaurl", "--out", tmp_path / "o" / "x")
    assert_one_error_line(result, "--scheduler", "notaurl", "no port number")
    assert not (tmp_path / "o").exists()


def test_malformed_scheduler_is_refused_before_any_connection(inputs, tmp_path, monkeypatch, capsys):
    """The address's form is checked first: no Client is ever built for it (a half-built one is what waited)."""
    pytest.importorskip("distributed")
    import ddsgen.distributed

    connections = []
    monkeypatch.setattr(ddsgen.distributed, "connect", lambda *args, **kwargs: connections.append(args))
    preset, scenes = inputs
    code = main(["render", preset, "--scenes", scenes, "-n", "2", "--scheduler", "notaurl", "--out",
                 str(tmp_path / "o" / "x"), "--quiet"])  # fmt: skip
    assert code == 2 and "no port number" in capsys.readouterr().err
    assert connections == []


def test_failed_connection_leaves_no_half_built_client(tmp_path):
    """A well-formed address whose Client fails to start: one InputError, then a clean and quick exit (the half-built
    Client's __del__ used to wait 2 x the timeout at exit and print an 'Exception ignored' traceback; how long it
    takes now: bench/bench_edges.py)."""
    pytest.importorskip("distributed")
    code = ("from ddsgen.distributed import connect\n"
            "from ddsgen.errors import InputError\n"
            "try:\n    connect('inproc://192.0.2.1/1/1', timeout=3)\n"
            "except InputError as error:\n    print(error)\n")  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("--scheduler: cannot connect to inproc://"), result.stdout
    assert result.stderr == "", result.stderr


# ---------------------------------------------------------------- 3. truncated / corrupt images: our line only


def _depth_png_bytes(height: int = 48, width: int = 64) -> bytes:
    """A valid 16-bit depth PNG (mm) with some texture, so that its image data spans many bytes."""
    from ddsgen.io.png import depth_to_units
    import cv2

    rng = np.random.default_rng(3)
    depth = depth_to_units(rng.uniform(0.5, 2.0, (height, width)))
    ok, data = cv2.imencode(".png", depth)
    assert ok
    return data.tobytes()


def _png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    import struct

    chunks, position = [], 8
    while position < len(data):
        (length,) = struct.unpack_from(">I", data, position)
        chunks.append((data[position + 4 : position + 8], data[position + 8 : position + 8 + length]))
        position += 12 + length
    return chunks


def _png_from_chunks(chunks) -> bytes:
    import struct
    import zlib

    return b"\x89PNG\r\n\x1a\n" + b"".join(struct.pack(">I", len(body)) + kind + body
                                          + struct.pack(">I", zlib.crc32(kind + body)) for kind, body in chunks)  # fmt: skip


def _bad_filter_png() -> bytes:
    """Every chunk intact (CRCs valid), but the rows' filter bytes say 9 (valid: 0-4): libpng's 'bad adaptive filter
    value', which no structural check can see."""
    import zlib

    chunks = _png_chunks(_depth_png_bytes())
    width = int.from_bytes(chunks[0][1][:4], "big")
    raw = bytearray(zlib.decompress(b"".join(body for kind, body in chunks if kind == b"IDAT")))
    raw[:: 1 + 2 * width] = bytes([9]) * len(raw[:: 1 + 2 * width])
    rest = [c for c in chunks if c[0] not in (b"IDAT", b"IEND")]
    return _png_from_chunks([*rest, (b"IDAT", zlib.compress(bytes(raw))), (b"IEND", b"")])


def _flipped_png() -> bytes:
    """Bytes flipped inside the image data (the chunk's CRC no longer matches)."""
    data = bytearray(_depth_png_bytes())
    start = data.find(b"IDAT") + 20
    data[start : start + 30] = bytes(b ^ 0x5A for b in data[start : start + 30])
    return bytes(data)


BAD_PNGS = {
    "truncated": (lambda: _depth_png_bytes()[:300], "truncated: the file ends inside its IDAT chunk"),
    "flipped": (_flipped_png, "corrupt: CRC error in its IDAT chunk"),
    "bad_filter": (_bad_filter_png, "truncated or corrupt: bad adaptive filter value"),
}


@pytest.mark.parametrize("kind", sorted(BAD_PNGS))
def test_corrupt_depth_png_in_a_real_folder_is_our_line_only(kind, tmp_path):
    """fit --unpaired reads a plain depth folder: the line names the file and why, and nothing of libpng's or
    OpenCV's reaches stderr (they print to fd 2 from C, hence the subprocess)."""
    make, reason = BAD_PNGS[kind]
    real = tmp_path / "real"
    real.mkdir()
    (real / "0.png").write_bytes(make())
    result = run_cli("fit", "kinect_v1", real, "--unpaired", "--out", tmp_path / "fitted.yaml", "--quiet")
    assert_one_error_line(result, f"{real / '0.png'}: cannot read depth PNG ({reason}")
    assert not (tmp_path / "fitted.yaml").exists()


def test_read_image_reasons_and_fd2_restored(tmp_path, capfd):
    """In-process: each bad file is an InputError with its reason and nothing on fd 2; fd 2 works afterwards, also
    when the decode raised; what another writer put on fd 2 during a decode is passed on."""
    import cv2

    from ddsgen.io import images

    cases = {"empty.png": (b"", "(empty file)"), "text.png": (b"hello, not an image", "(not an image file OpenCV can decode)"),
             **{f"{k}.png": (make(), reason) for k, (make, reason) in BAD_PNGS.items()}}  # fmt: skip
    for name, (data, reason) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError, match=r"^.*" + name + r": cannot read depth PNG \(") as info:
            images.read_image(tmp_path / name, "depth PNG")
        assert reason in str(info.value)
    with pytest.raises(InputError, match=r"missing.png: cannot read image \(no such file\)"):
        images.read_image(tmp_path / "missing.png")
    good = tmp_path / "good.png"
    good.write_bytes(_depth_png_bytes())
    assert images.read_image(good).dtype == np.uint16
    assert capfd.readouterr().err == ""

    real_imdecode = cv2.imdecode

    def noisy_then_raise(data, flags):
        os.write(2, b"another thread's line\n")
        raise RuntimeError("boom")

    images.cv2.imdecode = noisy_then_raise
    try:
        with pytest.raises(RuntimeError):
            images.read_image(good)
    finally:
        images.cv2.imdecode = real_imdecode
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "another thread's line\nafter\n"


def test_png_check_reads_the_structure_without_decompressing(monkeypatch):
    """The structural check reads each chunk's CRC only, never inflating the image data: a small fraction of the
    decode it guards (measured in bench/bench_edges.py, png_check_vs_decode)."""
    from ddsgen.io import images
    from ddsgen.io.images import png_problem

    good, flipped, bad_filter = (np.frombuffer(make(), np.uint8) for make in
                                 (lambda: _depth_png_bytes(480, 640), _flipped_png, _bad_filter_png))  # fmt: skip

    def no_inflating(*args, **kwargs):
        raise AssertionError("png_problem decompressed the image data")

    monkeypatch.setattr(images.zlib, "decompress", no_inflating)
    monkeypatch.setattr(images.zlib, "decompressobj", no_inflating)
    assert png_problem(good) is None
    assert png_problem(flipped).startswith("corrupt: CRC error in its IDAT chunk")
    # the bad filter bytes sit inside intact compressed data: only the decode sees them
    assert png_problem(bad_filter) is None


# ---------------------------------------------------------------- 4-6. pattern and stereo: inputs and outputs first


def _main_fd(capfd, *argv) -> tuple[int, str]:
    """``main(ARGV)`` in this process; (exit code, everything on fd 2: C libraries included)."""
    from ddsgen.cli import main

    code = main([str(a) for a in argv])
    return code, capfd.readouterr().err


def _one_line(err: str, *fragments: str) -> None:
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("ddsgen: error: "), err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.mark.parametrize("bad", ["text", "truncated"])
def test_pattern_compare_is_read_before_the_pattern_is_written(bad, tmp_path, capfd):
    compare = tmp_path / "bad.png"
    compare.write_bytes(b"a text file\n" if bad == "text" else _depth_png_bytes()[:300])
    out = tmp_path / "o" / "pt.png"
    code, err = _main_fd(capfd, "pattern", "kinect_v1", "--compare", compare, "--out", out)
    assert code == 2
    _one_line(err, "--compare: ", f"{compare}: cannot read pattern image (")
    assert not out.exists() and not out.parent.exists(), "wrote the pattern although --compare is unreadable"


def test_output_below_a_plain_file_names_the_option_and_the_problem(tmp_path, capfd):
    afile = tmp_path / "afile"
    afile.write_text("a plain file\n")
    code, err = _main_fd(capfd, "pattern", "kinect_v1", "--out", afile / "p.png")
    assert code == 2
    _one_line(err, "--out: ", f"({afile} is a file, not a folder)")
    left, right = _stereo_pair(tmp_path)
    for option, name in (("--out", "d.exr"), ("--png", "p.png")):
        extra = ["--out", tmp_path / "d.exr"] if option == "--png" else []
        code, err = _main_fd(capfd, "stereo", left, right, "-D", "8", *extra, option, afile / name)
        assert code == 2
        _one_line(err, f"{option}: ", f"({afile} is a file, not a folder)")
    assert not (tmp_path / "d.exr").exists()


def _stereo_pair(folder: Path) -> tuple[Path, Path]:
    import cv2

    texture = (np.random.default_rng(0).random((32, 64)) * 255).astype(np.uint8)
    left, right = folder / "left.png", folder / "right.png"
    cv2.imwrite(str(left), texture)
    cv2.imwrite(str(right), np.roll(texture, -3, axis=1))
    return left, right


def test_stereo_refuses_an_output_name_whose_format_it_does_not_write(tmp_path, capfd):
    """--out x.png used to receive EXR bytes; --png x.jpg a JPEG. Both are refused before any matching."""
    left, right = _stereo_pair(tmp_path)
    code, err = _main_fd(capfd, "stereo", left, right, "-D", "8", "--out", tmp_path / "x.png")
    assert code == 2
    _one_line(err, "--out: ", "x.png", "EXR", "give a name ending in .exr", "--png")
    code, err = _main_fd(capfd, "stereo", left, right, "-D", "8", "--out", tmp_path / "d.exr", "--png", tmp_path / "x.jpg")
    assert code == 2
    _one_line(err, "--png: ", "x.jpg", "give a name ending in .png")
    assert not list(tmp_path.glob("x.*")) and not (tmp_path / "d.exr").exists()
    code, err = _main_fd(capfd, "stereo", left, right, "-D", "8", "--out", tmp_path / "D.EXR", "--png", tmp_path / "p.png")
    assert code == 0, err
    from ddsgen.io.exr import read_exr

    assert read_exr(tmp_path / "D.EXR").shape == (32, 64) and (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"


def test_stereo_truncated_image_is_our_line_only(tmp_path, capfd):
    left, right = _stereo_pair(tmp_path)
    right.write_bytes(right.read_bytes()[:200])
    code, err = _main_fd(capfd, "stereo", left, right, "-D", "8", "--out", tmp_path / "d.exr")
    assert code == 2
    _one_line(err, f"{right}: cannot read image (truncated")
