"""Batched frames and sharded rendering (`rtjax.batch`): equal to `rtjax.render` bit for bit.

The several-device checks run in a process of their own with 4 forced host devices
(`tests/multidevice.py render`; XLA reads the flag when JAX starts), launched once and
in the background while the in-process tests run; these assert its results.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from test_cli import SMALL, render_main, write_deck

import rtjax
from rtjax import batch, cli
from rtjax.sunraster import read_sunraster

HERE = os.path.dirname(os.path.abspath(__file__))


def launch(*args: str, popen=subprocess.Popen, env: dict[str, str] | None = None) -> subprocess.Popen:
    """tests/multidevice.py in a fresh process with 4 forced CPU devices (started by
    `popen`, e.g. a conftest.Job's), in `env` (default: this process's). `rtjax.tune_cpu`
    appends its own XLA flag to XLA_FLAGS, so the forced device count survives."""
    env = dict(os.environ if env is None else env)
    flags = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()
    env.update(XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    return popen([sys.executable, os.path.join(HERE, "multidevice.py"), *args], env=env,
                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def collect(proc: subprocess.Popen, timeout: float = 600) -> dict:
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def four(tmp_path_factory):
    """The 4-device checks, started when first asked for; the result when done."""
    proc = launch("render", str(tmp_path_factory.mktemp("four")))
    box: dict = {}

    def result() -> dict:
        if not box:
            box.update(collect(proc))
        return box

    yield result
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


def test_start_the_four_device_checks(four):
    """(Starts them early: the in-process tests below run meanwhile.)"""


# ---- in-process (one device) ----------------------------------------------------------


SWEEP = SMALL + "rend a.ras\neyep -8 6 4\nrend b.ras\nelig 0.5\nrend c.ras\nsize 12\nrend d.ras\n"


@pytest.fixture
def batch_calls(monkeypatch) -> list[int]:
    """The frame count of every `batch.render_batch` call made during the test."""
    calls = []
    real = batch.render_batch

    def counting(structure, params, **kw):
        calls.append(int(np.shape(params.ke)[0]))
        return real(structure, params, **kw)

    monkeypatch.setattr(batch, "render_batch", counting)
    return calls


@pytest.mark.slow
def test_frames_sharing_a_structure_render_in_one_call(batch_calls):
    scenes = [f.scene for f in rtjax.parse_deck(SWEEP).frames]
    assert [i for _, i in batch.group_by_structure(scenes)] == [[0, 1, 2], [3]]
    images = rtjax.render_frames(scenes)
    assert batch_calls == [3]  # the three 16-pixel-wide frames in one call; the 12-pixel one alone
    for scene, image in zip(scenes, images):
        assert np.array_equal(np.asarray(image), np.asarray(rtjax.render(scene)))
    assert np.shape(images[3]) == (9, 12, 3)


@pytest.mark.slow
def test_a_parameter_sweep_is_one_batched_call():
    scene = rtjax.parse_deck(SMALL + "rend a.ras\n").frames[0].scene
    kes = np.linspace(0.0, 1.0, 5, dtype=np.float32)
    params = rtjax.stack_params([scene.replace(ke=k).params for k in kes])
    images = np.asarray(rtjax.render_batch(scene.structure, params, mode="vmap"))
    assert images.shape == (5, 12, 16, 3)
    for k, image in zip(kes, images):
        assert np.array_equal(image, np.asarray(rtjax.render(scene.replace(ke=k))))
    assert not np.array_equal(images[0], images[-1])
    assert np.array_equal(np.asarray(rtjax.render_batch(scene.structure, params, mode="map")), images)


@pytest.mark.slow
def test_a_sweep_in_the_silhouette_mode_equals_render():
    """Whole frames in the silhouette mode go through `render`'s own path (pixels near
    edges chosen from the plain trace's keys, above 4096 pixels): bit for bit, in one
    call mapped over the frames."""
    scene = rtjax.parse_deck(SMALL + "rend a.ras\n").frames[0].scene.resized(80)
    assert scene.structure.width * scene.structure.height > 4096
    kes = np.array([0.1, 0.6], np.float32)
    params = rtjax.stack_params([scene.replace(ke=k).params for k in kes])
    images = np.asarray(rtjax.render_batch(scene.structure, params, edges=1.0, mode="map"))
    for k, image in zip(kes, images):
        assert np.array_equal(image, np.asarray(rtjax.render(scene.replace(ke=k), edges=1.0)))


@pytest.mark.slow
def test_a_sweep_with_sub_boxes_equals_render():
    """`subdivide` reaches the batched render: each frame equals `render`'s with its
    2 × 2 sub-boxes in the mirror, bit for bit (and they change the image)."""
    mirror = SMALL.replace("opaq 0 0.5 1 0 1", "mirr") + "rend a.ras\n"
    scene = rtjax.parse_deck(mirror).frames[0].scene.resized(24)
    kes = np.array([0.1, 0.6], np.float32)
    params = rtjax.stack_params([scene.replace(ke=k).params for k in kes])
    images = np.asarray(rtjax.render_batch(scene.structure, params, edges=1.0, subdivide=True, mode="map"))
    for k, image in zip(kes, images):
        assert np.array_equal(image, np.asarray(rtjax.render(scene.replace(ke=k), edges=1.0, subdivide=True)))
    assert np.abs(images[0] - np.asarray(rtjax.render(scene.replace(ke=kes[0]), edges=1.0, subdivide=0))).max() > 0.5


def test_batches_are_cut_to_bound_memory():
    s = rtjax.parse_deck(SMALL + "rend a.ras\n").frames[0].scene.structure
    assert [len(c) for c in batch.batch_chunks(s, 10, batch=4)] == [4, 4, 2]
    big = s.replace(width=400, height=294)
    assert [len(c) for c in batch.batch_chunks(big, 40)] == [17, 17, 6]  # 2^21 samples a call
    assert [len(c) for c in batch.batch_chunks(big, 40, devices=4)] == [40]


def test_cli_renders_shared_structures_batched(tmp_path, capsys, batch_calls):
    """Frames 0-2 share a structure: one batched call, each line reporting a third of its
    time; the files equal frame-by-frame rendering (`--batch 1`)."""
    deck = write_deck(tmp_path, SWEEP)
    code, stdout, err = render_main(capsys, deck, "-o", tmp_path / "batched")
    assert code == 0, err
    assert batch_calls == [3]
    lines = stdout.splitlines()
    assert [line.split()[0] for line in lines] == [str(tmp_path / "batched" / f"{c}.ras") for c in "abcd"]
    assert len({line.split()[-2] for line in lines[:3]}) == 1  # the call's time, shared equally
    code, stdout, err = render_main(capsys, deck, "-o", tmp_path / "single", "--batch", "1")
    assert code == 0, err
    assert batch_calls == [3]  # --batch 1: no batched call
    for c in "abcd":
        assert np.array_equal(read_sunraster(tmp_path / "batched" / f"{c}.ras"), read_sunraster(tmp_path / "single" / f"{c}.ras"))


def test_cli_more_devices_than_there_are_is_one_line(tmp_path, capsys):
    import jax

    n = len(jax.devices()) + 1
    deck = write_deck(tmp_path, SMALL + "rend a.ras\n")
    code, stdout, err = render_main(capsys, deck, "-o", tmp_path / "out", "--devices", str(n))
    assert code == 2 and stdout == ""
    lines = err.splitlines()
    assert len(lines) == 1 and f"{n} devices asked for, {n - 1} available" in lines[0], err
    assert not (tmp_path / "out").exists()
    with pytest.raises(SystemExit) as info:
        cli.main(["render", deck, "--devices", "0"])
    assert info.value.code == 2
    assert len(capsys.readouterr().err.splitlines()) == 1


# ---- four forced host devices (the subprocess) --------------------------------------------


@pytest.mark.slow
def test_sharded_sample_deck_equals_single_device_bit_for_bit(four):
    r = four()
    assert r["devices"] == 4 and r["platform"] == "cpu"
    assert r["sample_shape"] == [294, 400, 3]  # full size: 294 rows dealt out to 4 devices (padded to 296)
    assert r["sample_sharding_devices"] == 4
    assert r["sample_full_4"] is True


@pytest.mark.slow
def test_batched_multi_frame_deck_equals_frame_by_frame(four):
    r = four()
    assert r["multi_batched_1"] == [True, True, True]  # one device, lax.map inside the call (a CPU's default)
    assert r["multi_vmap_1"] == [True, True, True]  # one device, vmap
    assert r["multi_frames_4"] == [True, True, True]  # frames over 4 devices (3 padded to 4)
    assert r["multi_pixels_4"] == [True, True, True]  # every frame's pixels over 4 devices, vmapped


@pytest.mark.slow
def test_cli_devices_4_writes_the_frame_by_frame_images(four):
    r = four()
    assert r["cli_code"] == 0
    assert r["cli_files"] == [True, True, True]
