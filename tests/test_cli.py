"""`rtjax render`: the sample deck end to end as a subprocess, the rest in-process.

A few runs are real subprocesses (`python -m rtjax render ...`), which is what a user
types; JAX start-up costs about two seconds a process, so the other cases call
`rtjax.cli.main([...])` in-process, on one small scene structure (one compilation).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

import rtjax

from rtjax import cli
from rtjax.sunraster import read_sunraster

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SAMPLE = os.path.join(ROOT, "scenes", "ex2s3.dat")

#: A small opaque scene: one compiled structure serves every in-process render below.
SMALL = (
    "sphe 0 0 0 1\nopaq 1 0.2 0 0.5 10\n"
    "sphe 0 0 2.5 1\nopaq 0 0.5 1 0 1\n"
    "plig 1 1 2 255 255 255\nback 0 0 128\nelig 0.2\n"
    "eyep 8 6 4\nrefp 0 0 1\nvang 40 30\nsize 16\n"
)  # 11 lines
LINE = re.compile(r"^(\S+(?: \+ \S+)*)  (\d+)x(\d+)  (\d+\.\d\d) s$")


def run_cli(*args: str, cwd: str | os.PathLike | None = None, **env_vars: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, JAX_PLATFORMS="cpu", **env_vars)
    return subprocess.run([sys.executable, "-m", "rtjax", *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=300)


def write_deck(folder, text: str, name: str = "d.dat") -> str:
    path = os.path.join(folder, name)
    with open(path, "w") as f:
        f.write(text)
    return path


def pil_rgb(path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def all_files(folder) -> list[str]:
    """Every file under `folder`, hidden ones (temporary files) included, relative."""
    out = []
    for root, _, files in os.walk(folder):
        out += [os.path.relpath(os.path.join(root, f), folder) for f in files]
    return sorted(out)


def one_error_line(err: str, prefix: str) -> str:
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(prefix), lines[0]
    return lines[0]


# ---- subprocesses -----------------------------------------------------------------------


def test_sample_deck_renders_a_sun_raster_pillow_reads(tmp_path):
    out = tmp_path / "out"
    proc = run_cli("render", SAMPLE, "-o", str(out), "--png")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == 1
    m = LINE.match(lines[0])
    assert m and m.group(1) == f"{out / 'ex2s3.sunimg'} + {out / 'ex2s3.png'}" and m.group(2, 3) == ("400", "294")
    assert all_files(out) == ["ex2s3.png", "ex2s3.sunimg"]
    raw = (out / "ex2s3.sunimg").read_bytes()
    assert raw[:4] == bytes.fromhex("59a66a95") and len(raw) == 32 + 3 * 400 * 294
    with Image.open(out / "ex2s3.sunimg") as im:
        assert im.format == "SUN" and im.size == (400, 294)
    rgb = pil_rgb(out / "ex2s3.sunimg")
    for corner in (rgb[0, 0], rgb[0, -1], rgb[-1, 0], rgb[-1, -1]):
        assert tuple(corner) == (0, 0, 128)  # the dark-blue background, not dark red
    assert np.array_equal(pil_rgb(out / "ex2s3.png"), rgb)  # the preview is the same picture
    assert np.array_equal(read_sunraster(out / "ex2s3.sunimg"), rgb)
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 1000  # a rendered scene, not a flat fill


@pytest.mark.slow
def test_compiled_programs_are_kept_between_runs(tmp_path):
    """RTJAX_CACHE names the folder where the command keeps XLA's compiled programs; a
    second run of the same deck loads them and writes the same image."""
    cache, out = tmp_path / "cache", tmp_path / "out"
    first = run_cli("render", SAMPLE, "-o", str(out / "1"), RTJAX_CACHE=str(cache))
    assert first.returncode == 0, first.stderr
    kept = sorted(os.listdir(cache))
    assert kept and any("render" in name for name in kept)
    second = run_cli("render", SAMPLE, "-o", str(out / "2"), RTJAX_CACHE=str(cache))
    assert second.returncode == 0, second.stderr
    assert sorted(os.listdir(cache)) == kept  # nothing compiled anew
    assert (out / "1" / "ex2s3.sunimg").read_bytes() == (out / "2" / "ex2s3.sunimg").read_bytes()


@pytest.mark.parametrize("env, expected", [
    ({"RTJAX_CACHE": "/somewhere"}, "/somewhere"),
    ({"RTJAX_CACHE": "off"}, None),
    ({"XDG_CACHE_HOME": "/xdg"}, os.path.join("/xdg", "rtjax", "xla")),
])
def test_cache_dir_follows_the_environment(monkeypatch, env, expected):
    monkeypatch.delenv("RTJAX_CACHE", raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    assert rtjax.xla.cache_dir() == expected


def test_bad_deck_subprocess_exit_2_one_line_nothing_written(tmp_path):
    deck = write_deck(tmp_path, SMALL.replace("opaq 0 0.5 1 0 1", "opaq 0 0.5 1 0") + "rend a.ras\n", "bad.dat")
    out = tmp_path / "out"
    proc = run_cli("render", deck, "-o", str(out))
    assert proc.returncode == 2
    assert proc.stdout == ""
    line = one_error_line(proc.stderr, "bad.dat:4: ")
    assert line == "bad.dat:4: opaq takes 5 numbers (dR dG dB ks beta), found 4: 0 0.5 1 0"
    assert not out.exists()


# ---- in-process -------------------------------------------------------------------------


def render_main(capsys, *args) -> tuple[int, str, str]:
    code = cli.main(["render", *map(str, args)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_several_rend_lines_several_files_one_line_each(tmp_path, capsys):
    deck = write_deck(tmp_path, SMALL + "rend a.ras\neyep -8 6 4\nrend sub/b.sunimg\nsize 12\nrend c.png\n")
    out = tmp_path / "new" / "folder"
    code, stdout, err = render_main(capsys, deck, "-o", out)
    assert code == 0 and err == ""
    lines = stdout.splitlines()
    assert len(lines) == 3
    want = [(out / "a.ras", 16, 12), (out / "sub" / "b.sunimg", 16, 12), (out / "c.png", 12, 9)]
    for line, (path, w, h) in zip(lines, want):
        m = LINE.match(line)
        assert m and m.group(1) == str(path) and (int(m.group(2)), int(m.group(3))) == (w, h), line
        assert float(m.group(4)) >= 0
        assert pil_rgb(path).shape == (h, w, 3)
    assert all_files(out) == ["a.ras", "c.png", "sub/b.sunimg"]
    a, b = read_sunraster(out / "a.ras"), read_sunraster(out / "sub" / "b.sunimg")
    assert tuple(a[0, 0]) == (0, 0, 128) and not np.array_equal(a, b)  # the camera moved


def test_png_preview_beside_each_sun_raster(tmp_path, capsys):
    deck = write_deck(tmp_path, SMALL + "rend a.ras\nrend b.png\n")
    code, stdout, _ = render_main(capsys, deck, "-o", tmp_path / "o", "--png")
    assert code == 0
    assert all_files(tmp_path / "o") == ["a.png", "a.ras", "b.png"]  # a PNG output gets no second PNG
    assert stdout.splitlines()[0].startswith(f"{tmp_path / 'o' / 'a.ras'} + {tmp_path / 'o' / 'a.png'}  16x12  ")
    assert np.array_equal(pil_rgb(tmp_path / "o" / "a.png"), read_sunraster(tmp_path / "o" / "a.ras"))


def test_default_outdir_is_the_current_folder(tmp_path, capsys, monkeypatch):
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    code, stdout, _ = render_main(capsys, deck)
    assert code == 0 and stdout.startswith("a.ras  16x12  ")
    assert all_files(tmp_path / "cwd") == ["a.ras"]


BAD_DECKS = [
    ("unknown", SMALL + "rend a.ras\nfrob 1\n", 13, "unknown command 'frob'"),
    ("range", SMALL.replace("elig 0.2", "elig 2") + "rend a.ras\n", 7, "elig: ke must be in [0, 1], found 2"),
    ("nan", SMALL.replace("refp 0 0 1", "refp 0 nan 1") + "rend a.ras\n", 9, "refp: yf must be a finite number, found nan"),
    ("no-material", SMALL + "sphe 1 1 1 1\nrend a.ras\n", 12, "sphe has no material line after it"),
    ("camera", SMALL.replace("size 16", "") + "rend a.ras\n", 12, "rend: the camera is incomplete: size must come before rend"),
    ("late-error", SMALL + "rend a.ras\nrend b.ras\nback 0 0 999\nrend c.ras\n", 14, "back: BB must be in [0, 255], found 999"),
    ("absolute", SMALL + "rend a.ras\nrend /tmp/rtjax-test-abs.ras\n", 13, "output path '/tmp/rtjax-test-abs.ras' is absolute; pass --allow-any-path"),
    ("dotdot", SMALL + "rend a.ras\nrend ../escape.ras\n", 13, "output path '../escape.ras' leaves the output folder; pass --allow-any-path"),
    ("dotdot-inside", SMALL + "rend sub/../../x.ras\n", 12, "leaves the output folder"),
    ("extension", SMALL + "rend a.ras\nrend b.xyz\n", 13, "b.xyz: no image format for this extension"),
    ("no-extension", SMALL + "rend a.ras\nrend picture\n", 13, "picture: no image format for this extension"),
    ("large", SMALL.replace("size 16", "size 20000") + "rend a.ras\n", 12, "beyond 16384 pixels a side; pass --allow-large"),
]


@pytest.mark.parametrize("text, line, fragment", [b[1:] for b in BAD_DECKS], ids=[b[0] for b in BAD_DECKS])
def test_bad_decks_exit_2_and_write_nothing(tmp_path, capsys, monkeypatch, text, line, fragment):
    def no_render(*a, **k):
        raise AssertionError("nothing may be rendered for a deck that is refused")

    monkeypatch.setattr(rtjax.batch, "render", no_render)
    deck = write_deck(tmp_path, text, "bad.dat")
    out = tmp_path / "out"
    out.mkdir()
    code, stdout, err = render_main(capsys, deck, "-o", out)
    assert code == 2 and stdout == ""
    message = one_error_line(err, f"bad.dat:{line}: ")
    assert fragment in message
    assert all_files(out) == []  # the first frame, fine on its own, was not rendered either
    assert not os.path.exists("/tmp/rtjax-test-abs.ras") and not (tmp_path / "escape.ras").exists()


def test_cli_errors_without_a_line(tmp_path, capsys):
    code, _, err = render_main(capsys, tmp_path / "missing.dat")
    assert code == 2 and one_error_line(err, "missing.dat: cannot read the deck: ")
    deck = write_deck(tmp_path, SMALL, "norend.dat")
    code, _, err = render_main(capsys, deck, "-o", tmp_path / "out")
    assert code == 2 and one_error_line(err, "norend.dat: the deck has no rend line")
    (tmp_path / "latin1.dat").write_bytes(b"# caf\xe9\n")
    code, _, err = render_main(capsys, tmp_path / "latin1.dat")
    assert code == 2 and one_error_line(err, "latin1.dat:1: the deck is not UTF-8 text (byte 0xe9)")
    assert not (tmp_path / "out").exists()


def test_outdir_that_is_a_file(tmp_path, capsys):
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    (tmp_path / "afile").write_text("keep me")
    code, stdout, err = render_main(capsys, deck, "-o", tmp_path / "afile")
    assert code == 2 and stdout == ""
    one_error_line(err, "d.dat:12: rend a.ras: ")
    assert (tmp_path / "afile").read_text() == "keep me"


@pytest.mark.parametrize("argv", [["--spp", "0"], ["--depth", "-1"], ["--dtype", "float16"], ["--edges", "99"], ["--bogus"],
                                  ["--edges", "1", "--subdivide", "5"]])
def test_bad_options_are_one_line(tmp_path, capsys, argv):
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    with pytest.raises(SystemExit) as info:
        cli.main(["render", deck, "-o", str(tmp_path / "out"), *argv])
    assert info.value.code == 2
    err = capsys.readouterr().err
    one_error_line(err, "rtjax")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, says", [
    (["--loss-scale", "-1"], "rtjax fit: argument --loss-scale: expected a number > 0, found -1"),
    (["--loss-scale", "x"], "rtjax fit: argument --loss-scale: expected a number, found 'x'"),
    (["--levels", "0"], "levels must be a count ≥ 1 or widths ≥ 1 pixel, not 0"),
    (["--levels", "0,32"], "levels must be a count ≥ 1 or widths ≥ 1 pixel, not [0, 32]"),
])
def test_bad_fit_options_are_one_line(tmp_path, capsys, argv, says):
    """Refused before the target is read or anything is compiled; nothing is written."""
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    args = ["fit", deck, str(tmp_path / "target.png"), "-o", str(tmp_path / "out" / "f.dat"), *argv]
    try:
        code = cli.main(args)
    except SystemExit as info:  # argparse's own refusals
        code = info.code
    assert code == 2
    assert capsys.readouterr().err == says + "\n"
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("target, argv, says", [
    ("missing.png", [], "missing.png"),
    ("square.png", [], "the aspect ratios differ"),
    ("right.png", ["--spheres", "7"], "sphere index 7 is out of range"),
    ("right.png", ["--free", "textures"], "the scene has no textured spheres"),
    ("right.png", ["--mask", "square.png"], "the mask is 16×16, the target 16×12"),
])
def test_bad_fit_inputs_are_refused_before_the_wait(tmp_path, capsys, target, argv, says):
    """A target that cannot be read or is of the wrong shape, a mask that does not fit it,
    and a selection the deck lacks, are one line and exit 2 before the line that says
    the first step waits for the compile (that line came first, then the error)."""
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(tmp_path / "square.png")
    Image.fromarray(np.zeros((12, 16, 3), np.uint8)).save(tmp_path / "right.png")
    argv = [str(tmp_path / a) if a.endswith(".png") else a for a in argv]
    code = cli.main(["fit", deck, str(tmp_path / target), "-o", str(tmp_path / "out" / "f.dat"), *argv])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert says in one_error_line(captured.err, "")
    assert not (tmp_path / "out").exists()


def test_fit_is_given_the_target_and_mask_as_read(tmp_path, capsys, monkeypatch):
    """`rtjax fit` reads the target and the mask once, before it says it waits, and hands
    the fit their pixels and weights (the mask's dark pixels weigh 0)."""
    import fitting

    seen = {}

    def fit(scene, target, free, *, spheres, options, callback):
        seen.update(target=target, mask=options.mask)
        raise fitting.FitError("stopped here")

    monkeypatch.setattr(fitting, "fit", fit)
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    pixels = np.arange(12 * 16 * 3, dtype=np.uint8).reshape(12, 16, 3)
    Image.fromarray(pixels).save(tmp_path / "t.png")
    dark = np.full((12, 16), 255, np.uint8)
    dark[:, :5] = 0
    Image.fromarray(dark).save(tmp_path / "m.png")
    code = cli.main(["fit", deck, str(tmp_path / "t.png"), "--mask", str(tmp_path / "m.png"), "--quiet"])
    assert code == 2 and capsys.readouterr().err == "stopped here\n"
    np.testing.assert_array_equal(seen["target"], pixels)
    np.testing.assert_array_equal(seen["mask"][..., 0], (dark / 255.0))


@pytest.mark.parametrize("command, flag, what", [("bench", "-o", "the benchmark's outputs"),
                                                ("fit", "-o", "the fit's outputs")])
def test_an_output_folder_below_a_file_is_refused_first(tmp_path, capsys, command, flag, what):
    """`rtjax bench` and `rtjax fit` run for minutes: an output folder they could not
    write is one line and exit 2 before they start (it was a traceback at the end)."""
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    (tmp_path / "file").write_text("keep me")
    out = tmp_path / "file" / "out"
    args = [command, deck] + ([str(tmp_path / "target.png")] if command == "fit" else ["--quick"])
    code = cli.main(args + [flag, str(out / "f.dat") if command == "fit" else str(out)])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert captured.err == f"{out}: cannot write {what} there: {tmp_path / 'file'} is not a folder\n"
    assert (tmp_path / "file").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.dat", "file"]


def test_absolute_and_dotdot_paths_with_allow_any_path(tmp_path, capsys):
    target = tmp_path / "elsewhere" / "abs.ras"
    deck = write_deck(tmp_path, SMALL + f"rend {target}\nrend ../up.ras\n")
    code, stdout, err = render_main(capsys, deck, "-o", tmp_path / "out", "--allow-any-path")
    assert code == 0, err
    assert read_sunraster(target).shape == (12, 16, 3)
    assert read_sunraster(tmp_path / "up.ras").shape == (12, 16, 3)
    assert len(stdout.splitlines()) == 2


def test_dtype_float64(tmp_path, capsys):
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    assert render_main(capsys, deck, "-o", tmp_path / "f32")[0] == 0
    code, stdout, _ = render_main(capsys, deck, "-o", tmp_path / "f64", "--dtype", "float64")
    assert code == 0 and stdout.startswith(f"{tmp_path / 'f64' / 'a.ras'}  16x12  ")
    a = read_sunraster(tmp_path / "f32" / "a.ras").astype(int)
    b = read_sunraster(tmp_path / "f64" / "a.ras").astype(int)
    assert np.mean(np.abs(a - b) <= 1) > 0.99  # the same picture up to rounding
    assert tuple(b[0, 0]) == (0, 0, 128)


def test_assignment_order_swaps_red_and_blue_for_pillow(tmp_path, capsys):
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    assert render_main(capsys, deck, "-o", tmp_path / "std")[0] == 0
    assert render_main(capsys, deck, "-o", tmp_path / "asg", "--assignment-order")[0] == 0
    std, asg = pil_rgb(tmp_path / "std" / "a.ras"), pil_rgb(tmp_path / "asg" / "a.ras")
    assert tuple(std[0, 0]) == (0, 0, 128) and tuple(asg[0, 0]) == (128, 0, 0)  # dark blue shows dark red
    assert np.array_equal(asg, std[:, :, ::-1])
    raw = (tmp_path / "asg" / "a.ras").read_bytes()
    assert raw[32:35] == bytes([0, 0, 128])  # R, G, B as the assignment's struct wrote them


def test_non_finite_render_is_an_error_not_an_image(tmp_path, capsys, monkeypatch):
    import jax.numpy as jnp

    def nan_render(scene, **kw):
        s = scene.structure
        return jnp.full((s.height, s.width, 3), 10.0).at[3, 4, 1].set(jnp.nan)

    monkeypatch.setattr(rtjax.batch, "render", nan_render)
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    code, stdout, err = render_main(capsys, deck, "-o", tmp_path / "out", "--png")
    assert code == 2 and stdout == ""
    assert one_error_line(err, "d.dat:12: rend a.ras: ").endswith("image has 1 non-finite values")
    assert not (tmp_path / "out").exists()


def test_allow_large_without_rendering_a_huge_image(tmp_path, capsys, monkeypatch):
    import jax.numpy as jnp

    from rtjax.camera import image_height

    height = image_height(16385, 40, 30)
    assert height == 12062
    deck = write_deck(tmp_path, SMALL.replace("size 16", "size 16385") + "rend a.ras\n")
    code, _, err = render_main(capsys, deck, "-o", tmp_path / "out")
    assert code == 2
    assert one_error_line(err, f"d.dat:12: rend: the image would be 16385×{height}, beyond 16384 pixels a side; pass --allow-large")
    seen = []

    def stub(scene, **kw):
        seen.append((scene.structure.width, scene.structure.height))
        return jnp.zeros((2, 2, 3))

    monkeypatch.setattr(rtjax.batch, "render", stub)
    code, stdout, err = render_main(capsys, deck, "-o", tmp_path / "out", "--allow-large")
    assert code == 0, err
    assert seen == [(16385, height)]
    assert stdout.startswith(f"{tmp_path / 'out' / 'a.ras'}  16385x{height}  ")
    assert cli.MAX_SIDE == 16384


@pytest.mark.parametrize("command, says", [("render", "d.dat:12: rend a.ras: "), ("fit", "fitting at 16×12 pixels: "),
                                            ("bench", "rtjax bench: ")])
def test_out_of_memory_is_one_line(tmp_path, capsys, monkeypatch, command, says):
    """XLA's allocator failing in a render, a fit or a benchmark (too large for the
    machine) is one line, exit 2, nothing written (a fit's and a benchmark's were
    tracebacks)."""
    import fitting
    import rtjax.bench

    def oom(*args, **kw):
        raise RuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 123456789 bytes.\nmore detail")

    for module, name in ((rtjax.batch, "render"), (fitting, "fit"), (rtjax.bench, "main_bench")):
        monkeypatch.setattr(module, name, oom)
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    Image.fromarray(np.zeros((12, 16, 3), np.uint8)).save(tmp_path / "t.png")
    args = {"render": ["-o", str(tmp_path / "out")], "bench": ["-o", str(tmp_path / "out")],
            "fit": [str(tmp_path / "t.png"), "-o", str(tmp_path / "out" / "f.dat"), "--quiet"]}[command]
    code = cli.main([command, deck, *args])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    line = one_error_line(captured.err, says + "out of memory (RESOURCE_EXHAUSTED")
    assert line.endswith("bytes. more detail)")
    assert not (tmp_path / "out").exists()


def test_edges_reaches_the_renderer(tmp_path, capsys, monkeypatch):
    import jax.numpy as jnp

    calls = []

    def with_edges(scene, *, depth=None, spp=1, dtype=None, edges=0.0, subdivide=None):
        calls.append((edges, spp, subdivide))
        return jnp.zeros((scene.structure.height, scene.structure.width, 3))

    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    monkeypatch.setattr(rtjax.batch, "render", with_edges)
    assert render_main(capsys, deck, "-o", tmp_path / "out", "--edges", "1.5", "--spp", "2")[0] == 0
    assert render_main(capsys, deck, "-o", tmp_path / "out", "--edges", "1", "--subdivide")[0] == 0
    assert render_main(capsys, deck, "-o", tmp_path / "out", "--edges", "1", "--subdivide", "2")[0] == 0
    assert calls == [(1.5, 2, None), (1.0, 1, 1), (1.0, 1, 2)]  # None: `render`'s default
    code, _, err = render_main(capsys, deck, "-o", tmp_path / "out", "--subdivide")
    assert code != 0 and "subdivide needs the silhouette-aware mode" in err, err
