"""The command line's failures: every error one line on stderr and an exit code, nothing lost.

Operating-system errors are produced for real where the machine allows it: a file in the way,
a folder an unprivileged user cannot write (the command runs as ``nobody`` when the tests run
as root), a read-only and a full file system (small tmpfs mounts, where this process may
mount). Where it does not, the error is raised inside the command by a patched writer, which
still checks the command's handling.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import omniscape_torch as ot
from omniscape_torch import cli

from test_calibration_fit import _write

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["--frames", "2", "--image-size", "16", "--max-face-size", "16", "--cameras",
         "fisheye_left", "--no-progress"]


def _line(err: str) -> str:
    """The one error line of a command's stderr (other lines are progress messages)."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("omniscape-torch ")]
    assert len(lines) == 1, err
    return lines[0]


def _command(*args: str) -> list[str]:
    return [sys.executable, "-m", "omniscape_torch.cli", *args]


# --------------------------------------------------------------------------------------------
# A path in the way
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["generate", "convert", "fit"])
@pytest.mark.parametrize("under", [False, True])
def test_an_output_path_blocked_by_a_file_is_one_line_and_exit_1(tmp_path, capsys, command,
                                                                 under):
    blocker = tmp_path / "a_file"
    blocker.write_text("mine")
    out = blocker / "sub" if under else blocker
    argv = {"generate": ["generate", "--out", str(out), *SMALL],
            "convert": ["convert", "--cubemaps", str(tmp_path), "--out", str(out)],
            "fit": ["fit", str(_write(tmp_path, n_views=4, rows=4, cols=5)[2]), "--model",
                    "equidistant", "--out", str(out), "--no-progress"]}[command]
    assert cli.main(argv) == 1
    line = _line(capsys.readouterr().err)
    assert f"{blocker}: a file is in the way" in line
    assert blocker.read_text() == "mine"


# --------------------------------------------------------------------------------------------
# Permissions, read-only and full file systems (real ones where the machine allows)
# --------------------------------------------------------------------------------------------

def _as_nobody():
    """``preexec_fn`` that drops root to the ``nobody`` user."""
    os.setgid(65534)
    os.setuid(65534)


def test_a_folder_without_write_permission(tmp_path, capsys, monkeypatch):
    """Run as ``nobody`` when the tests run as root and that user can run this Python; else
    (a root whose Python lies in a private folder) the permission check is told the folder is
    not writable, as it is for an ordinary user."""
    import shutil
    import tempfile

    folder = Path(tempfile.mkdtemp(prefix="omniscape-perm-"))   # outside pytest's 0700 tree
    home = Path(tempfile.mkdtemp(prefix="omniscape-home-"))
    try:
        folder.chmod(0o555)
        home.chmod(0o777)
        kwargs = {"preexec_fn": _as_nobody} if os.geteuid() == 0 else {}
        env = {**os.environ, "HOME": str(home), "PYTHONPATH": str(ROOT)}
        try:
            done = subprocess.run(_command("generate", "--out", str(folder / "ds"), *SMALL),
                                  capture_output=True, text=True, env=env, cwd=home,
                                  timeout=300, **kwargs)
            real = "Error" not in done.stderr.split("omniscape-torch")[0]
        except PermissionError:   # nobody may not run this Python
            real = False
        if real:
            assert done.returncode == 1, done.stderr
            line = _line(done.stderr)
        else:
            writable = os.access
            monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if Path(path) ==
                                folder else writable(path, mode, **kw))
            assert cli.main(["generate", "--out", str(folder / "ds"), *SMALL]) == 1
            line = _line(capsys.readouterr().err)
        assert f"{folder}: permission denied" in line
        assert list(folder.iterdir()) == []
    finally:
        folder.chmod(0o755)
        shutil.rmtree(folder, ignore_errors=True)
        shutil.rmtree(home, ignore_errors=True)


@pytest.fixture
def tmpfs(tmp_path):
    """``mount(options)``: a tmpfs mounted under ``tmp_path`` (skips where mounting is not
    permitted); unmounted afterwards."""
    mounted = []

    def mount(options: str) -> Path:
        point = tmp_path / f"mnt{len(mounted)}"
        point.mkdir()
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(point)],
                              capture_output=True)
        if done.returncode != 0:
            pytest.skip("mounting a tmpfs is not permitted here")
        mounted.append(point)
        return point

    yield mount
    for point in mounted:
        subprocess.run(["umount", "-l", str(point)], capture_output=True)


def test_a_read_only_file_system(tmpfs, capsys):
    point = tmpfs("ro,size=1m")
    assert cli.main(["generate", "--out", str(point / "ds"), *SMALL]) == 1
    assert f"{point}: the file system is read-only" in _line(capsys.readouterr().err)


@pytest.mark.slow
def test_a_full_disk_mid_run(tmpfs, tmp_path):
    """The disk fills while frames are written: one line naming the file and the advice,
    exit 1; every file present is whole (written atomically), and on a disk with room the
    same command finishes the dataset."""
    point = tmpfs("size=160k")
    out = point / "ds"
    argv = ["generate", "--out", str(out), "--frames", "6", "--image-size", "64",
            "--max-face-size", "32", "--cameras", "fisheye_left", "--no-progress"]
    done = subprocess.run(_command(*argv), capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 1, done.stderr
    line = _line(done.stderr)
    assert "no space left on the device" in line and str(out) in line
    for png in out.rglob("*.png"):
        ot.io.read_image(png)                      # whole, or not there
    subprocess.run(["mount", "-o", "remount,size=8m", str(point)], check=True)
    again = subprocess.run(_command(*argv), capture_output=True, text=True, timeout=300,
                           env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert again.returncode == 0, again.stderr
    assert len(list((out / ".done").iterdir())) == 6


def test_any_os_error_inside_a_command_becomes_one_line(tmp_path, capsys, monkeypatch):
    """Wherever the machine cannot give a full disk: the error raised by a writer inside the
    run (here ENOSPC from the PNG writer) is handled the same way."""
    import omniscape_torch.data.generate as dataset

    def full(path, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(dataset, "write_image", full)
    assert cli.main(["generate", "--out", str(tmp_path / "ds"), *SMALL]) == 1
    line = _line(capsys.readouterr().err)
    assert "rgb/000000.png: no space left on the device" in line


def test_generate_without_pillow_fails_at_once_naming_the_install(tmp_path, capsys,
                                                                 monkeypatch):
    """Pillow writes the PNGs (a requirement; a broken install may still lack it): a run
    without it stops before any work, in one line that says what to install, and leaves no
    folder behind."""
    monkeypatch.setitem(sys.modules, "PIL", None)      # `from PIL import Image` raises
    out = tmp_path / "never"
    assert cli.main(["generate", "--out", str(out), *SMALL]) == 1
    line = _line(capsys.readouterr().err)
    assert "needs Pillow" in line and "pip install pillow" in line
    assert not out.exists()


#: Runs the command line with OpenCV and matplotlib unimportable (``None`` in ``sys.modules``),
#: as in ``pip install omniscape_torch`` with no extras: each command line of argv (separated
#: by ``--next``) in turn, printing ``exit <code>`` after each.
_WITHOUT_OPTIONAL = """
import sys
sys.modules.update(cv2=None, matplotlib=None)
from omniscape_torch.cli import main
argv, commands = sys.argv[1:], [[]]
for a in argv:
    commands.append([]) if a == "--next" else commands[-1].append(a)
for c in commands:
    print(f"exit {main(c)}", flush=True)
assert "cv2" not in [m for m in sys.modules if sys.modules[m] is not None]
"""


@pytest.mark.slow
def test_the_main_commands_run_without_opencv_and_matplotlib(tmp_path):
    """generate, stats, info and convert with neither OpenCV nor matplotlib (the bare install,
    simulated where CI has both): all exit 0; stats prints its tables, writes stats.json and
    says in one line which extra draws stats.png."""
    from omniscape_torch.cubemap import FACES
    from omniscape_torch.io import write_image

    captures = tmp_path / "cubemaps" / "000001"
    for face in FACES:
        write_image(captures / f"{face}_rgb.png", np.full((8, 8, 3), 90, np.uint8))
        write_image(captures / f"{face}_depth.png", np.full((8, 8, 3), (0, 0, 10), np.uint8))
        write_image(captures / f"{face}_labels.png", np.full((8, 8, 3), (7, 0, 0), np.uint8))
    ds = tmp_path / "ds"
    argv = ["generate", "--out", str(ds), *SMALL, "--next", "stats", str(ds), "--next", "info",
            "--next", "convert", "--cubemaps", str(tmp_path / "cubemaps"), "--out",
            str(tmp_path / "conv"), "--size", "16", "16", "--no-progress"]
    proc = subprocess.run([sys.executable, "-c", _WITHOUT_OPTIONAL, *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert [ln for ln in proc.stdout.splitlines() if ln.startswith("exit ")] == ["exit 0"] * 4, \
        proc.stdout + proc.stderr
    assert "Table I: vehicle attitude" in proc.stdout
    assert ('stats.png not drawn (it needs matplotlib): pip install "omniscape_torch[plot]"'
            in proc.stdout.splitlines())
    assert (ds / "stats.json").is_file() and not (ds / "stats.png").exists()
    assert (ds / "contact_sheet.png").is_file()
    assert (tmp_path / "conv" / "000001" / "fisheye_rgb.png").is_file()


def test_an_unexpected_error_is_one_line_or_a_traceback_when_asked(tmp_path, capsys,
                                                                   monkeypatch):
    import omniscape_torch.data.generate as dataset

    def broken(*args, **kwargs):
        raise RuntimeError("something\nbroke")

    monkeypatch.setattr(dataset.FrameRenderer, "render", broken)
    assert cli.main(["generate", "--out", str(tmp_path / "ds"), *SMALL]) == 1
    assert _line(capsys.readouterr().err).endswith("error: RuntimeError: something broke")
    assert cli.main(["--traceback", "generate", "--out", str(tmp_path / "ds2"), *SMALL]) == 1
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and 'raise RuntimeError("something' in err
    assert err.splitlines()[-1].endswith("error: RuntimeError: something broke")


def test_traceback_keeps_the_exit_code_of_bad_input(tmp_path, capsys):
    argv = ["fit", str(tmp_path / "missing.txt"), "--model", "equidistant", "--out",
            str(tmp_path / "out")]
    assert cli.main(argv) == 2
    line = capsys.readouterr().err.strip()
    assert cli.main(["--traceback", *argv]) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and err.splitlines()[-1] == line


# --------------------------------------------------------------------------------------------
# Ctrl-C
# --------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2])
def test_ctrl_c_stops_within_2_s_says_what_is_kept_and_the_rerun_renders_the_rest(tmp_path,
                                                                                 workers):
    """Ctrl-C once a frame is finished: exit 130 within 2 s with any number of workers (the
    workers finish or drop the frame in flight: no half-written file, no temporary left),
    a line saying how many frames are kept, and the same command renders only the rest."""
    import re

    out = tmp_path / "ds"
    frames = 40
    argv = ["generate", "--out", str(out), "--frames", str(frames), "--image-size", "32",
            "--max-face-size", "32", "--cameras", "fisheye_left", "catadioptric_left",
            "--workers", str(workers), "--no-progress"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    # SIGINT's default in the child: a shell that starts a job in the background (`cmd &`)
    # makes it ignored, Python keeps it so, and the run could not be interrupted (skipped)
    proc = subprocess.Popen(_command(*argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 240

    def markers() -> list[str]:
        done = out / ".done"
        return sorted(p.name for p in done.iterdir() if p.name.isdigit()) if done.is_dir() \
            else []

    sent = time.monotonic()
    while proc.poll() is None and time.monotonic() < deadline:
        if markers():
            sent = time.monotonic()
            proc.send_signal(signal.SIGINT)
            break
        time.sleep(0.01)
    proc.wait(timeout=240)
    elapsed = time.monotonic() - sent
    _, err = proc.communicate()
    finished = markers()
    if len(finished) == frames:
        pytest.skip("the run finished before it could be interrupted")
    assert proc.returncode == 130, err
    assert elapsed < 2.0, f"exit {elapsed:.2f} s after SIGINT"
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    kept = re.fullmatch(rf"omniscape-torch generate: interrupted: (\d+) of {frames} frames "
                        rf"kept in {re.escape(str(out))}; run the same command again to render "
                        rf"the rest", line)
    assert kept, line
    assert int(kept[1]) == len(finished) >= 1
    left = [p for p in out.rglob(".*") if p.is_file() and p.parent.name != ".done"]
    assert not left, left                       # no temporary of the dropped frames, no lock
    for png in out.rglob("*.png"):
        ot.io.read_image(png)                   # every file there is whole
    again = subprocess.run(_command(*argv), capture_output=True, text=True, env=env,
                           timeout=300)
    assert again.returncode == 0, again.stderr
    assert f"skipped {len(finished)} finished" in again.stdout
    assert len(markers()) == frames


# --------------------------------------------------------------------------------------------
# fit: the result is never lost
# --------------------------------------------------------------------------------------------

def test_a_fit_whose_output_cannot_be_written_keeps_its_result(tmp_path, capsys, monkeypatch):
    """The output fails after the fit (a full disk, simulated in the writer that installs the
    files): the camera is kept in a temporary folder whose path is printed, exit 1, and the
    output folder holds nothing half-written."""
    truth, _, path = _write(tmp_path, model="scaramuzza", n_views=5, rows=6, cols=8)
    out = tmp_path / "out"

    def full(files, folder):
        Path(folder).mkdir(parents=True, exist_ok=True)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(Path(folder) / "camera.json"))

    # the installer of the fit's files, where Calibration.write calls it
    monkeypatch.setattr(sys.modules["omniscape_torch.calibration.calibrate"], "publish", full)
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--out", str(out),
                     "--no-progress"]) == 1
    line = _line(capsys.readouterr().err)
    assert "no space left on the device" in line
    kept = Path(line.split("the fitted camera is kept in ")[1])
    try:
        camera = ot.Camera.load_json(kept / "camera.json")
        assert json.loads((kept / "camera.json").read_text())["fit"]["converged"]
        assert camera.model.name == "scaramuzza"
        assert ot.Camera.from_ocamcalib(kept / "calib_results.txt").params.shape == \
            camera.params.shape
        assert list(out.iterdir()) == []
    finally:
        import shutil
        shutil.rmtree(kept, ignore_errors=True)


def test_fit_writes_all_its_files_or_none(tmp_path, capsys, monkeypatch):
    """A writer that fails after another one succeeded (here OCamCalib's file after the JSON)
    leaves the output folder untouched."""
    from omniscape_torch.cameras import Camera

    _, _, path = _write(tmp_path, model="scaramuzza", n_views=5, rows=6, cols=8)
    out = tmp_path / "out"

    def failing(self, *args, **kwargs):
        raise ValueError("calib_results.txt: the inverse polynomial missed its target")

    monkeypatch.setattr(Camera, "to_ocamcalib", failing)
    assert cli.main(["fit", str(path), "--model", "scaramuzza", "--out", str(out),
                     "--no-progress"]) == 2
    assert "inverse polynomial" in _line(capsys.readouterr().err)
    assert not out.exists() or list(out.iterdir()) == []


# --------------------------------------------------------------------------------------------
# Exit codes as documented (tests/README.md): 2 for bad input, a missing file included
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, message", [
    (["info", "--ocamcalib", "{tmp}/missing.txt"], "no calibration file at {tmp}/missing.txt"),
    (["info", "--json", "{tmp}/missing.json"], "{tmp}/missing.json: no such file or folder"),
    (["convert-model", "--ocamcalib", "{tmp}/missing.txt", "--to", "eucm"],
     "no calibration file at {tmp}/missing.txt"),
    (["fit", "{tmp}/missing_points.txt", "--model", "equidistant", "--out", "{tmp}/out"],
     "{tmp}/missing_points.txt: no such correspondence file"),
    (["stats", "{tmp}/no_dataset"], "no dataset.json"),
])
def test_a_missing_input_file_is_one_line_and_exit_2(tmp_path, capsys, argv, message):
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert cli.main(argv) == 2
    line = _line(capsys.readouterr().err)
    assert line.startswith(f"omniscape-torch {argv[0]}: error: ")
    assert message.format(tmp=tmp_path) in line
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# Usage errors: one line, not argparse's usage block
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, line", [
    (["generate", "--out", "x", "--image-size", "4"],
     "omniscape-torch generate: error: argument --image-size: expected N or HxW pixels, each "
     "at least 8, got '4'; see omniscape-torch generate --help"),
    (["generate"], "omniscape-torch generate: error: the following arguments are required: "
                   "--out; see omniscape-torch generate --help"),
    (["fit", "points.txt", "--out", "x", "--model", "nope"], None),
    (["no-such-command"], None),
    ([], "omniscape-torch: error: the following arguments are required: COMMAND; see "
         "omniscape-torch --help"),
])
def test_a_usage_error_is_one_line_ending_with_see_help_and_exit_2(capsys, argv, line):
    with pytest.raises(SystemExit) as exit_:
        cli.main(argv)
    assert exit_.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1, captured.err
    prefix = "omniscape-torch" + (f" {argv[0]}" if argv[:1] in (["generate"], ["fit"]) else "")
    assert lines[0].startswith(f"{prefix}: error: ")
    assert lines[0].endswith(f"; see {prefix} --help")
    if line is not None:
        assert lines[0] == line


def test_help_still_prints_the_usage(capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["generate", "--help"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith("usage: omniscape-torch generate")


# --------------------------------------------------------------------------------------------
# The parser: at once, without torch, every option explained
# --------------------------------------------------------------------------------------------

#: Every usage a newcomer tries first: the helps and a few argument errors.
_QUICK = [["--help"], *[[name, "--help"] for name in cli.build_parser()._subparsers
                        ._group_actions[0].choices],
          ["fit", "--model", "nope", "--out", "x"], ["generate", "--image-size", "4"],
          ["convert-model", "--to", "nope"], ["generate", "--out", "x", "--shard", "5/2"], []]


def test_help_and_usage_errors_import_neither_torch_nor_numpy():
    """`omniscape-torch --help` answers at once: the parser is built and the arguments
    parsed before anything heavy is imported (issue 46: 4 s before, torch imported first)."""
    script = f"""
import sys
from omniscape_torch import cli
for argv in {_QUICK!r}:
    try:
        cli.main(argv)
    except SystemExit as exit_:
        assert exit_.code == (0 if "--help" in argv else 2), (argv, exit_.code)
    else:
        raise AssertionError(argv)
heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "numpy", "cv2", "PIL"))
print("heavy:", heavy, file=sys.stderr)
"""
    start = time.perf_counter()
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    elapsed = time.perf_counter() - start
    assert run.returncode == 0, run.stderr
    assert run.stderr.splitlines()[-1] == "heavy: []", run.stderr
    assert elapsed < 10, elapsed   # 0.1-0.2 s idle; torch alone takes 3 s on a loaded machine


def _parsers(parser=None):
    """The top-level parser and every sub-command's."""
    parser = parser or cli.build_parser()
    yield parser
    for action in parser._actions:
        if isinstance(action, __import__("argparse")._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


def test_every_option_and_command_has_help_text():
    checked = 0
    for parser in _parsers():
        for action in parser._actions:
            if isinstance(action, __import__("argparse")._SubParsersAction):
                for choice in action._choices_actions:   # each sub-command's line
                    assert choice.help and choice.help.strip(), f"{parser.prog} {choice.dest}"
                continue
            assert action.help and action.help.strip(), (
                f"{parser.prog} {'/'.join(action.option_strings) or action.dest}: no help")
            checked += 1
        assert parser.description, f"{parser.prog}: no description"
    assert checked > 80


def test_the_top_level_help_shows_examples_and_the_guides(capsys):
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    out = capsys.readouterr().out
    examples = out.split("examples:")[1].split("guides")[0]
    assert sum(line.strip().startswith("omniscape-torch ")
               for line in examples.splitlines()) == 3
    guides = {word for word in out.split() if word.startswith("docs/")}
    assert {"docs/getting-started.md", "docs/calibration.md", "docs/datasets.md",
            "docs/troubleshooting.md"} <= guides
    assert all((ROOT / g).is_file() for g in guides), guides
    assert "``" not in out   # no reST literals
    for parser in _parsers():   # every guide a sub-command names exists; no source file named
        text = parser.format_help()
        assert ".py" not in text.replace("notebooks/02", ""), parser.prog
        assert all((ROOT / w.rstrip(".,;)")).is_file() for w in text.split()
                   if w.startswith("docs/")), parser.prog
    generate_help = next(p for p in _parsers() if p.prog.endswith(" generate")).format_help()
    assert "docs/datasets.md" in generate_help


def test_the_parser_tables_are_the_packages():
    """The names the parser offers are written in cli.py (so that parsing needs no torch);
    each must equal the package's own table, which a new model, format or weather changes."""
    from omniscape_torch.calibration import LOSSES, METHODS
    from omniscape_torch.cameras import MODELS, READ_FORMATS
    from omniscape_torch.cameras.export import FORMATS, supported_models
    from omniscape_torch.data import captures, generate, woodscape
    from omniscape_torch.io.carla import LABEL_SETS
    from omniscape_torch.scenes import town

    assert cli.LENS_MODELS == tuple(m for m in MODELS if m != "equirectangular")
    assert cli.READ_FORMATS == tuple(READ_FORMATS)
    assert tuple(cli.WRITE_FORMATS) == tuple(FORMATS)
    assert supported_models("json") == tuple(MODELS) and cli.WRITE_FORMATS["json"] == ("any",)
    assert all(cli.WRITE_FORMATS[f] == supported_models(f) for f in FORMATS if f != "json")
    assert cli.FIT_METHODS == tuple(METHODS) and cli.FIT_LOSSES == tuple(LOSSES)
    assert cli.RIG_CAMERAS == tuple(generate.CAMERAS)
    assert cli.RIGS == tuple(generate.RIGS)
    assert cli.WOODSCAPE_CAMERAS == tuple(woodscape.CAMERAS)
    assert cli.DATASET_FORMATS == tuple(generate.FORMATS)
    assert cli.CAPTURE_CAMERAS == tuple(captures.CAMERAS)
    assert cli.CARLA_PRESETS == tuple(town.CARLA_PRESETS)
    assert cli.WEATHERS == tuple(town.WEATHERS) and cli.LAYOUTS == dict(town.LAYOUTS)
    assert cli.LABEL_SETS == tuple(LABEL_SETS)


def test_a_busy_folder_is_one_plain_line(tmp_path, capsys):
    from omniscape_torch.io.atomic import folder_lock

    out = tmp_path / "busy"
    with folder_lock(out):
        assert cli.main(["generate", "--out", str(out), *SMALL]) == 1
    line = _line(capsys.readouterr().err)
    assert line.startswith(f"omniscape-torch generate: error: {out}: another run (process "), line
