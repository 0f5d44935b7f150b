"""Make the photo-like evaluation set in scenes/photos/: images of deck scenes rendered by
three independent, physically based renderers (POV-Ray 3.7, Blender Cycles, Mitsuba 3),
passed through a seeded camera model, with a truth deck and a perturbed start deck per photo.
Mitsuba's photos are all held out: the fitting was tuned on POV-Ray's and Cycles' only.

A tool, run by hand; nothing in rtjax, fitting or the tests imports it.

Install the renderers (Debian 12 packages, POV-Ray 3.7.0 and Blender 3.4.1; Mitsuba
and SciPy from PyPI into the virtual environment):

    apt-get install -y povray blender
    pip install mitsuba scipy

Run from the worktree's virtual environment (which has rtjax, OpenImageIO, Pillow, SciPy):

    python scripts/make_photos.py                   # render what is not cached, develop, write all
    python scripts/make_photos.py --only glass      # one deck, one renderer or one photo name only
    python scripts/make_photos.py --force           # render again even if cached
    python scripts/make_photos.py --check-geometry  # camera check against rtjax (silhouettes)

Renders (linear OpenEXR) are cached in build/photos/renders/ (git-ignored); photos, start
decks and manifest.json are written to scenes/photos/. Every random choice is seeded, so a
run writes the same manifest, decks and (renders being equal) photos; POV-Ray's radiosity
on two threads and Cycles' sampling are the renderers' own.

What the converters do:

* Camera: DECK.md section 2 exactly (eye, look-at, z up with y standing in when looking
  straight along z, horizontal view angle ha, vertical extent from va, square pixels as
  the deck defines them). POV-Ray gets explicit `direction`/`right`/`up` vectors (no
  look_at, so its left-handed y-up default plays no part); Blender gets the camera matrix
  with columns (u, v, -w), `sensor_fit` horizontal, `angle_x` = ha, and a pixel aspect
  that makes the vertical extent exactly tan(va/2) however the image height was rounded.
* Materials: `opaq` is a plastic (POV-Ray: diffuse, Blinn `specular` ks with roughness
  1/(4 beta), a Fresnel clear coat when beta >= 20; Cycles: Principled BSDF, specular
  min(1, 2.5 ks), roughness (2/(4 beta + 2))^(1/4)); `mirr` is a perfect metal (white,
  sharp); `trpa` is Fresnel glass of index n whose transmission is tinted by kt at each
  interface (shadows pass kt per interface in both renderers, without caustics); its
  glint is POV-Ray's Blinn `specular` ks, and Cycles' reflection of the sun's disc.
* Colours: the deck's d, light colours / 255 and back / 255 are display (sRGB-encoded)
  values, decoded to linear light for the renderers, so an sRGB tone curve shows them
  as the deck gives them.
* Lights: each `plig` is a sun with a 2 degree disc (POV-Ray: a far circular area light;
  Cycles: a sun lamp) giving (1 - ke) L on a white surface facing it (L linear).
* Sky: `back` is what camera rays, reflections and refractions see; diffuse light comes
  from a uniform sky of radiance ke (sum of L + back), linear (POV-Ray: radiosity with a
  `no_image no_reflection` emitting dome; Cycles: the world shader split by Light Path).
* Mitsuba 3 (`scalar_rgb`, its `path` integrator, Gaussian pixel filter) has models of
  its own: `opaq` is `roughplastic` (Beckmann alpha sqrt(2 / (4 beta + 2)), specular
  scale min(1, 5 ks)), `mirr` polished aluminium (`conductor`, measured Al), `trpa` a
  `dielectric` of index n transmitting kt per interface (glass casts a real shadow: no
  light passes it to a shadow ray), each `plig` a `directional` light (hard shadows) of
  irradiance pi (1 - ke) L, and `back` a `constant` sky that camera rays see and that
  lights the scene (there is no separate ambient term). Its camera has square pixels
  only, so its photos' truth decks are decks/NAME-mitsuba.dat: NAME.dat with va set so
  that tan(va/2) = tan(ha/2) H / W exactly (H unchanged, va moved by at most 0.05 deg).
* Camera model (after rendering, per photo, seeded): exposure, white-balance gains, lens
  blur (Gaussian), vignetting, sensor noise (shot + read) in linear light; then a tone
  curve (sRGB, a plain gamma, Blender's Filmic view transform, or for Mitsuba's photos
  the ACES filmic fit of Narkowicz 2015 before sRGB); then 8-bit JPEG
  (quality 50-95, 4:2:0 or 4:4:4 chroma) or PNG.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
import zlib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "scenes", "photos")
DECKS = os.path.join(OUT, "decks")
STARTS = os.path.join(OUT, "starts")
CACHE = os.path.join(ROOT, "build", "photos")
SCRIPT = os.path.abspath(__file__)

SEED = 20240611
DECK_NAMES = ("floor_spheres", "mirrors", "glass", "two_lights", "top_down", "ex2s3", "mixed")
RENDERERS = ("povray", "cycles")  # the renderers of the tuning set and its hold-out
#: A third renderer, every photo of it held out.
THIRD = "mitsuba"
#: (deck, renderer) pairs that get a second camera model (a second photo of one render).
SECOND_MODEL = (("floor_spheres", "cycles"), ("mirrors", "povray"), ("glass", "cycles"), ("ex2s3", "povray"))
TONES = ("srgb", "gamma", "filmic")
THIRD_TONES = ("aces", "srgb", "gamma")
MITSUBA_SPP = 192
EX2S3_WIDTH = 320
SUN_ANGLE_DEG = 2.0
FLOOR_FACTOR = 10.0  # a sphere whose radius exceeds this many times the median is a floor
OFFSET_RANGE = (0.05, 0.15)  # start-deck centre offsets, fractions of the radius
CYCLES_SAMPLES = 160
POV_AA = ("+A0.03", "+AM2", "+R3", "+J0.5")
POV_RADIOSITY = "pretrace_start 0.08 pretrace_end 0.01 count 200 nearest_count 10 error_bound 0.5 recursion_limit 2 low_error_factor 0.5 gray_threshold 0 brightness 1"
NICE = ("nice", "-n", "15")


# -- decks -------------------------------------------------------------------------------------
def write_ex2s3_copy() -> None:
    """decks/ex2s3.dat: the assignment's sample deck with `size` set to the photo width."""
    with open(os.path.join(ROOT, "scenes", "ex2s3.dat"), encoding="utf-8") as f:
        lines = f.read().splitlines()
    out = ["##### ex2s3.dat #####", f"# Photo set (f): scenes/ex2s3.dat, the assignment's sample deck, with size {EX2S3_WIDTH}."]
    for line in lines:
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if words[0] == "size":
            line = f"size {EX2S3_WIDTH}"
        elif words[0] == "rend":
            line = "rend ex2s3.sunimg"
        out.append(line)
    text = "\n".join(out) + "\n"
    path = os.path.join(DECKS, "ex2s3.dat")
    if not os.path.exists(path) or open(path, encoding="utf-8").read() != text:
        with open(path, "w", encoding="utf-8") as f:
            f.write(text)


def square_va(ha: float, width: int, height: int) -> float:
    """The vertical view angle (degrees) that makes a width × height image's pixels square."""
    return math.degrees(2 * math.atan(math.tan(math.radians(ha) / 2) * height / width))


def square_pixel_deck(deck: str) -> str:
    """Write decks/DECK-mitsuba.dat: decks/DECK.dat with `vang`'s va set so that pixels are
    square (tan(va/2) = tan(ha/2) H / W for the deck's own H), which Mitsuba's camera needs.
    Returns the new deck's name."""
    path = os.path.join(DECKS, deck + ".dat")
    scene = load_scene(path)
    width, height = scene.structure.width, scene.structure.height
    ha = float(scene.params.vang[0])
    va = square_va(ha, width, height)
    lines = open(path, encoding="utf-8").read().splitlines()
    out = [f"# {deck}-{THIRD}.dat: {deck}.dat with square pixels for Mitsuba's camera (scripts/make_photos.py)"]
    out += [f"vang {ha:.10g} {va:.10g}" if line.split()[:1] == ["vang"] else line for line in lines]
    name = f"{deck}-{THIRD}"
    text = "\n".join(out) + "\n"
    target = os.path.join(DECKS, name + ".dat")
    if not os.path.exists(target) or open(target, encoding="utf-8").read() != text:
        with open(target, "w", encoding="utf-8") as f:
            f.write(text)
    check = load_scene(target).structure
    if (check.width, check.height) != (width, height):
        raise SystemExit(f"make_photos: {target}: square pixels changed the image size to {check.width}x{check.height}")
    return name


def load_scene(path: str):
    import rtjax

    return rtjax.load_deck(path).frames[0].scene


def camera_basis(eye, refp):
    """Forward w, right u, up v of DECK.md section 2 (z up; y stands in when w is along z)."""
    import numpy as np

    w = np.asarray(refp, float) - np.asarray(eye, float)
    w /= np.linalg.norm(w)
    up = np.array([0.0, 0.0, 1.0])
    if np.sum(np.cross(w, up) ** 2) < 1e-20:
        up = np.array([0.0, 1.0, 0.0])
    u = np.cross(w, up)
    u /= np.linalg.norm(u)
    v = np.cross(u, w)
    return w, u, v


def describe(scene, mode: str = "photo") -> dict:
    """A renderer-neutral description of a scene (plain numbers, JSON-ready)."""
    import numpy as np

    s = scene.structure
    p = {k: np.asarray(getattr(scene.params, k), float) for k in ("centers", "radii", "diffuse", "ks", "beta", "kt", "ior", "light_dirs", "light_colors", "background", "ke", "eye", "refp", "vang")}
    if "tmap" in s.kinds:
        raise SystemExit("make_photos: textured spheres (tmap) are not converted; choose decks without them")
    w, u, v = camera_basis(p["eye"], p["refp"])
    ke = float(p["ke"])
    lights = [{"dir": (d / np.linalg.norm(d)).tolist(), "colour": srgb_to_linear(c / 255).tolist()} for d, c in zip(p["light_dirs"], p["light_colors"])]
    light_sum = sum(np.asarray(light["colour"]) for light in lights) if lights else np.zeros(3)
    back = srgb_to_linear(p["background"] / 255)
    spheres = []
    for i, kind in enumerate(s.kinds):
        spheres.append({
            "kind": kind, "center": p["centers"][i].tolist(), "radius": float(p["radii"][i]), "d": srgb_to_linear(p["diffuse"][i]).tolist(),
            "ks": float(p["ks"][i]), "beta": float(p["beta"][i]), "kt": float(p["kt"][i]), "n": float(p["ior"][i]),
        })
    return {
        "mode": mode, "width": s.width, "height": s.height, "eye": p["eye"].tolist(), "w": w.tolist(), "u": u.tolist(), "v": v.tolist(),
        "tan_h": math.tan(math.radians(p["vang"][0]) / 2), "tan_v": math.tan(math.radians(p["vang"][1]) / 2),
        "spheres": spheres, "lights": lights, "ke": ke, "back": back.tolist(), "sky": (ke * (light_sum + back)).tolist(),
        "median_radius": float(np.median(p["radii"])),
    }


def srgb_to_linear(x):
    """Deck colours (d, back, light colours over 255) are display values: linear light for the renderers."""
    import numpy as np

    x = np.clip(np.asarray(x, float), 0, 1)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def is_floor(sphere: dict, median_radius: float) -> bool:
    return sphere["radius"] > FLOOR_FACTOR * median_radius


# -- POV-Ray -----------------------------------------------------------------------------------
def pov_vec(x) -> str:
    return "<" + ", ".join(f"{float(c):.9g}" for c in x) + ">"


def pov_text(desc: dict) -> str:
    """POV-Ray 3.7 scene text for a description (mode "photo" or "mask")."""
    w, u, v = desc["w"], desc["u"], desc["v"]
    right = [2 * desc["tan_h"] * c for c in u]
    up = [2 * desc["tan_v"] * c for c in v]
    out = ["#version 3.7;"]
    if desc["mode"] == "photo":
        out.append(f"global_settings {{ assumed_gamma 1.0 max_trace_level 24 adc_bailout 0.001 radiosity {{ {POV_RADIOSITY} }} }}")
    else:
        out.append("global_settings { assumed_gamma 1.0 }")
    out.append("#default { finish { ambient 0 emission 0 diffuse 1 } }")
    out.append(f"camera {{ perspective location {pov_vec(desc['eye'])} direction {pov_vec(w)} right {pov_vec(right)} up {pov_vec(up)} }}")
    if desc["mode"] == "photo":
        out.append(f"background {{ rgb {pov_vec(desc['back'])} }}")
        # The diffuse sky: seen by radiosity (diffuse) rays only.
        out.append(f"sphere {{ <0, 0, 0>, 1e5 inverse hollow pigment {{ rgb {pov_vec(desc['sky'])} }} finish {{ emission 1 diffuse 0 }} no_image no_reflection no_shadow }}")
        far = 1e6
        size = 2 * far * math.tan(math.radians(SUN_ANGLE_DEG) / 2)
        for light in desc["lights"]:
            colour = [(1 - desc["ke"]) * c for c in light["colour"]]
            pos = [far * c for c in light["dir"]]
            out.append(f"light_source {{ {pov_vec(pos)}, rgb {pov_vec(colour)} area_light <{size:.6g}, 0, 0>, <0, {size:.6g}, 0>, 9, 9 adaptive 1 jitter circular orient }}")
    else:
        out.append("background { rgb 0 }")
    for i, s in enumerate(desc["spheres"]):
        out.append(f"sphere {{ {pov_vec(s['center'])}, {s['radius']:.9g} {pov_material(s, desc, i)} }}")
    return "\n".join(out) + "\n"


def pov_material(s: dict, desc: dict, index: int) -> str:
    if desc["mode"] == "mask":
        return f"pigment {{ rgb {pov_vec(mask_colour(index))} }} finish {{ emission 1 diffuse 0 }}"
    if s["kind"] == "mirr":
        return "pigment { rgb 1 } finish { diffuse 0 reflection { 1 } }"
    rough = 1 / (4 * s["beta"])
    if s["kind"] == "trpa":
        kt = s["kt"]
        return (f"pigment {{ rgbf <{kt:.6g}, {kt:.6g}, {kt:.6g}, 1> }} finish {{ diffuse 0 specular {s['ks']:.6g} roughness {rough:.6g} "
                f"reflection {{ 0, 1 fresnel on }} conserve_energy }} interior {{ ior {s['n']:.6g} }}")
    coat = " reflection { 0, 1 fresnel on } conserve_energy" if s["ks"] > 0 and s["beta"] >= 20 else ""
    return (f"pigment {{ rgb {pov_vec(s['d'])} }} finish {{ diffuse 1 specular {s['ks']:.6g} roughness {rough:.6g}{coat} }} "
            f"interior {{ ior 1.5 }}")


def pov_settings(mode: str) -> dict:
    aa = list(POV_AA) if mode == "photo" else ["+A0.0", "+AM2", "+R3", "-J"]
    return {"antialias": " ".join(aa), "radiosity": POV_RADIOSITY if mode == "photo" else None,
            "sun": f"area light 9x9 adaptive 1 jitter circular, {SUN_ANGLE_DEG} deg" if mode == "photo" else None}


def render_povray(desc: dict, exr: str) -> float:
    """Render with POV-Ray into a linear OpenEXR file; returns seconds."""
    pov = exr[:-4] + ".pov"
    with open(pov, "w") as f:
        f.write(pov_text(desc))
    aa = pov_settings(desc["mode"])["antialias"].split()
    cmd = [*NICE, "povray", f"+I{pov}", f"+O{exr}", "+FE", f"+W{desc['width']}", f"+H{desc['height']}", "-D", "-P", "+WT2", *aa]
    t = time.time()
    run(cmd, exr[:-4] + ".log")
    return time.time() - t


# -- Blender / Cycles ----------------------------------------------------------------------------
def beckmann_alpha(beta: float) -> float:
    """Beckmann alpha for a Phong exponent: Phong beta ~ Blinn 4 beta ~ Beckmann
    alpha^2 = 2 / (4 beta + 2)."""
    return math.sqrt(2 / (4 * beta + 2))


def cycles_roughness(beta: float) -> float:
    """Principled roughness for a Phong exponent: Blender's alpha is roughness squared."""
    return math.sqrt(beckmann_alpha(beta))


def cycles_settings(mode: str) -> dict:
    if mode == "photo":
        return {"samples": CYCLES_SAMPLES, "pixel_filter": "BLACKMAN_HARRIS 1.5 px", "denoising": False, "caustics": False,
                "clamp_indirect": 10.0, "sun_angle_deg": SUN_ANGLE_DEG, "bounces": "total 24, diffuse 3, glossy 16, transmission 16"}
    return {"samples": 256, "pixel_filter": "BOX 1 px", "denoising": False}


def render_cycles(desc: dict, exr: str, seed: int) -> float:
    """Render with Blender Cycles (headless) into a linear OpenEXR file; returns seconds."""
    job = exr[:-4] + ".json"
    with open(job, "w") as f:
        json.dump({"task": "render", "scene": desc, "out": exr, "seed": seed}, f)
    t = time.time()
    run([*NICE, "blender", "-b", "--factory-startup", "-t", "2", "-P", SCRIPT, "--", "--blender-job", job], exr[:-4] + ".log")
    if not os.path.exists(exr):
        raise SystemExit(f"make_photos: Blender wrote no {exr}; see {exr[:-4]}.log")
    return time.time() - t


def blender_main(job_path: str) -> None:
    """Inside Blender: carry out a job file (render a scene, or apply Filmic to images)."""
    import bpy

    with open(job_path) as f:
        job = json.load(f)
    if job["task"] == "filmic":
        sc = bpy.context.scene
        sc.view_settings.view_transform = "Filmic"
        sc.view_settings.exposure = 0.0
        sc.view_settings.gamma = 1.0
        sc.render.image_settings.file_format = "PNG"
        sc.render.image_settings.color_mode = "RGB"
        sc.render.image_settings.color_depth = "8"
        for item in job["items"]:
            sc.view_settings.look = item["look"]
            img = bpy.data.images.load(item["exr"])
            img.colorspace_settings.name = "Linear"
            img.save_render(item["png"], scene=sc)
        return
    blender_render(job["scene"], job["out"], job["seed"])


def blender_render(desc: dict, out: str, seed: int) -> None:
    import bmesh
    import bpy
    from mathutils import Matrix, Vector

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    photo = desc["mode"] == "photo"
    sc.render.engine = "CYCLES"
    cy = sc.cycles
    cy.device = "CPU"
    cy.samples = CYCLES_SAMPLES if photo else 256
    cy.use_adaptive_sampling = False
    cy.use_denoising = False
    cy.seed = seed
    cy.use_animated_seed = False
    cy.max_bounces, cy.diffuse_bounces, cy.glossy_bounces = 24, 3, 16
    cy.transmission_bounces, cy.transparent_max_bounces, cy.volume_bounces = 16, 16, 0
    cy.caustics_reflective = cy.caustics_refractive = False
    cy.sample_clamp_direct, cy.sample_clamp_indirect = 0.0, 10.0
    cy.pixel_filter_type = "BLACKMAN_HARRIS" if photo else "BOX"
    cy.filter_width = 1.5 if photo else 1.0
    sc.render.threads_mode = "FIXED"
    sc.render.threads = 2
    sc.render.use_persistent_data = False
    r = sc.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = desc["width"], desc["height"], 100
    # Vertical extent tan_v exactly: Blender's is tan_h * (H * aspect_y) / (W * aspect_x).
    ratio = desc["tan_v"] / desc["tan_h"] * desc["width"] / desc["height"]
    r.pixel_aspect_x, r.pixel_aspect_y = (1.0, ratio) if ratio >= 1 else (1 / ratio, 1.0)
    sc.view_settings.view_transform = "Standard"
    sc.view_settings.look = "None"
    sc.view_settings.exposure = 0.0
    r.image_settings.file_format = "OPEN_EXR"
    r.image_settings.color_mode = "RGB"
    r.image_settings.color_depth = "32"
    r.image_settings.exr_codec = "ZIP"
    r.filepath = out

    cam = bpy.data.cameras.new("camera")
    cam.sensor_fit = "HORIZONTAL"
    cam.angle_x = 2 * math.atan(desc["tan_h"])
    cam.clip_start, cam.clip_end = 0.01, 1e6
    cam_ob = bpy.data.objects.new("camera", cam)
    u, v, w, e = desc["u"], desc["v"], desc["w"], desc["eye"]
    cam_ob.matrix_world = Matrix([[u[k], v[k], -w[k], e[k]] for k in range(3)] + [[0, 0, 0, 1]])
    sc.collection.objects.link(cam_ob)
    sc.camera = cam_ob

    world = bpy.data.worlds.new("world")
    sc.world = world
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    wout = nt.nodes.new("ShaderNodeOutputWorld")
    if photo:
        # Camera, reflected and refracted rays see `back`; diffuse rays (and light sampling) the sky.
        seen, sky = nt.nodes.new("ShaderNodeBackground"), nt.nodes.new("ShaderNodeBackground")
        seen.inputs["Color"].default_value = (*desc["back"], 1)
        sky.inputs["Color"].default_value = (*desc["sky"], 1)
        lp = nt.nodes.new("ShaderNodeLightPath")
        m1, m2 = nt.nodes.new("ShaderNodeMath"), nt.nodes.new("ShaderNodeMath")
        m1.operation = m2.operation = "MAXIMUM"
        nt.links.new(lp.outputs["Is Camera Ray"], m1.inputs[0])
        nt.links.new(lp.outputs["Is Glossy Ray"], m1.inputs[1])
        nt.links.new(m1.outputs[0], m2.inputs[0])
        nt.links.new(lp.outputs["Is Transmission Ray"], m2.inputs[1])
        mix = nt.nodes.new("ShaderNodeMixShader")
        nt.links.new(m2.outputs[0], mix.inputs["Fac"])
        nt.links.new(sky.outputs[0], mix.inputs[1])
        nt.links.new(seen.outputs[0], mix.inputs[2])
        nt.links.new(mix.outputs[0], wout.inputs["Surface"])
        for k, light in enumerate(desc["lights"]):
            peak = max(light["colour"])
            if peak <= 0:
                continue
            ld = bpy.data.lights.new(f"sun{k}", "SUN")
            ld.energy = math.pi * (1 - desc["ke"]) * peak
            ld.color = [c / peak for c in light["colour"]]
            ld.angle = math.radians(SUN_ANGLE_DEG)
            lo = bpy.data.objects.new(f"sun{k}", ld)
            lo.rotation_euler = Vector(light["dir"]).to_track_quat("Z", "Y").to_euler()
            sc.collection.objects.link(lo)
    else:
        bg = nt.nodes.new("ShaderNodeBackground")
        bg.inputs["Strength"].default_value = 0.0
        nt.links.new(bg.outputs[0], wout.inputs["Surface"])

    for i, s in enumerate(desc["spheres"]):
        me = bpy.data.meshes.new(f"sphere{i}")
        bm = bmesh.new()
        bmesh.ops.create_icosphere(bm, subdivisions=7 if is_floor(s, desc["median_radius"]) else 6, radius=s["radius"])
        bm.to_mesh(me)
        bm.free()
        me.polygons.foreach_set("use_smooth", [True] * len(me.polygons))
        me.materials.append(blender_material(s, desc, i))
        ob = bpy.data.objects.new(f"sphere{i}", me)
        ob.location = s["center"]
        sc.collection.objects.link(ob)
    bpy.ops.render.render(write_still=True)


def blender_material(s: dict, desc: dict, index: int):
    import bpy

    mat = bpy.data.materials.new(f"m{index}")
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    if desc["mode"] == "mask":
        em = nt.nodes.new("ShaderNodeEmission")
        em.inputs["Color"].default_value = (*mask_colour(index), 1)
        em.inputs["Strength"].default_value = 1.0
        nt.links.new(em.outputs[0], out.inputs["Surface"])
    elif s["kind"] == "mirr":
        g = nt.nodes.new("ShaderNodeBsdfGlossy")
        g.distribution = "SHARP"
        g.inputs["Color"].default_value = (1, 1, 1, 1)
        nt.links.new(g.outputs[0], out.inputs["Surface"])
    elif s["kind"] == "trpa":
        kt = s["kt"]
        glass, clear = nt.nodes.new("ShaderNodeBsdfGlass"), nt.nodes.new("ShaderNodeBsdfTransparent")
        glass.distribution = "SHARP"
        glass.inputs["Color"].default_value = (kt, kt, kt, 1)
        glass.inputs["IOR"].default_value = s["n"]
        clear.inputs["Color"].default_value = (kt, kt, kt, 1)
        lp, mix = nt.nodes.new("ShaderNodeLightPath"), nt.nodes.new("ShaderNodeMixShader")
        nt.links.new(lp.outputs["Is Shadow Ray"], mix.inputs["Fac"])
        nt.links.new(glass.outputs[0], mix.inputs[1])
        nt.links.new(clear.outputs[0], mix.inputs[2])
        nt.links.new(mix.outputs[0], out.inputs["Surface"])
    else:
        b = nt.nodes.new("ShaderNodeBsdfPrincipled")
        b.inputs["Base Color"].default_value = (*s["d"], 1)
        b.inputs["Specular"].default_value = min(1.0, 2.5 * s["ks"])
        b.inputs["Roughness"].default_value = cycles_roughness(s["beta"])
        nt.links.new(b.outputs[0], out.inputs["Surface"])
    return mat


def mask_colour(index: int) -> list[float]:
    return [1.0 if k == index % 3 else 0.0 for k in range(3)]


# -- Mitsuba 3 ---------------------------------------------------------------------------------
def mitsuba_settings(mode: str) -> dict:
    if mode == "photo":
        return {"variant": "scalar_rgb", "integrator": "path, max_depth 24, rr_depth 8", "samples": MITSUBA_SPP, "pixel_filter": "gaussian (stddev 0.5 px)",
                "lights": "directional (no disc)", "sky": "constant = back, lights the scene"}
    return {"variant": "scalar_rgb", "integrator": "path, max_depth 1", "samples": 256, "pixel_filter": "box 1 px"}


def mitsuba_bsdf(s: dict, desc: dict) -> dict:
    def rgb(value):
        return {"type": "rgb", "value": [float(c) for c in value]}

    if desc["mode"] == "mask":
        return {"type": "diffuse", "reflectance": rgb([0, 0, 0])}
    if s["kind"] == "mirr":
        return {"type": "conductor", "material": "Al"}
    if s["kind"] == "trpa":
        return {"type": "dielectric", "int_ior": s["n"], "ext_ior": 1.0, "specular_transmittance": rgb([s["kt"]] * 3)}
    return {"type": "roughplastic", "distribution": "beckmann", "alpha": beckmann_alpha(s["beta"]), "int_ior": 1.5,
            "diffuse_reflectance": rgb(s["d"]), "specular_reflectance": rgb([min(1.0, 5 * s["ks"])] * 3)}


def render_mitsuba(desc: dict, exr: str, seed: int) -> float:
    """Render with Mitsuba 3 (`scalar_rgb`, in this process) into a linear OpenEXR file; returns seconds."""
    import mitsuba as mi
    import numpy as np

    mi.set_variant("scalar_rgb")
    photo = desc["mode"] == "photo"
    e, w, v = (np.asarray(desc[k], float) for k in ("eye", "w", "v"))
    if abs(desc["tan_v"] / desc["tan_h"] * desc["width"] / desc["height"] - 1) > 1e-7:
        raise SystemExit("make_photos: Mitsuba's camera has square pixels only; render a square-pixel deck (square_pixel_deck)")
    to_world = mi.ScalarTransform4f().look_at(origin=e.tolist(), target=(e + w).tolist(), up=v.tolist())
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 24, "rr_depth": 8} if photo else {"type": "path", "max_depth": 1},
        "sensor": {
            "type": "perspective", "fov_axis": "x", "fov": math.degrees(2 * math.atan(desc["tan_h"])), "near_clip": 0.01, "far_clip": 1e6,
            "to_world": to_world,
            "sampler": {"type": "independent", "sample_count": MITSUBA_SPP if photo else 256, "seed": seed},
            "film": {"type": "hdrfilm", "width": desc["width"], "height": desc["height"], "pixel_format": "rgb", "component_format": "float32",
                     "rfilter": {"type": "gaussian"} if photo else {"type": "box"}},
        },
    }
    if photo:
        scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": desc["back"]}}
        for k, light in enumerate(desc["lights"]):
            if max(light["colour"]) <= 0:
                continue
            scene[f"sun{k}"] = {"type": "directional", "direction": [-c for c in light["dir"]],
                                "irradiance": {"type": "rgb", "value": [math.pi * (1 - desc["ke"]) * c for c in light["colour"]]}}
    for i, s in enumerate(desc["spheres"]):
        shape = {"type": "sphere", "center": s["center"], "radius": s["radius"], "bsdf": mitsuba_bsdf(s, desc)}
        if not photo:
            shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": mask_colour(i)}}
        scene[f"sphere{i}"] = shape
    t = time.time()
    image = np.asarray(mi.render(mi.load_dict(scene), seed=seed), np.float64)[..., :3]
    write_exr(exr, image)
    return time.time() - t


# -- running renderers ---------------------------------------------------------------------------
def run(cmd: list[str], log: str) -> None:
    with open(log, "w") as f:
        res = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    if res.returncode != 0:
        raise SystemExit(f"make_photos: {cmd[len(NICE)]} failed (exit {res.returncode}); see {log}")


def read_exr(path: str):
    import numpy as np
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(path)
    if buf.has_error:
        raise SystemExit(f"make_photos: cannot read {path}: {buf.geterror()}")
    return np.asarray(buf.get_pixels(oiio.FLOAT))[..., :3].astype(np.float64)


def write_exr(path: str, image) -> None:
    import numpy as np
    import OpenImageIO as oiio

    h, w, _ = image.shape
    out = oiio.ImageOutput.create(path)
    out.open(path, oiio.ImageSpec(w, h, 3, oiio.FLOAT))
    out.write_image(np.ascontiguousarray(image, np.float32))
    out.close()


def render(desc: dict, renderer: str, exr: str, seed: int) -> float:
    os.makedirs(os.path.dirname(exr), exist_ok=True)
    if renderer == "povray":
        return render_povray(desc, exr)
    if renderer == THIRD:
        return render_mitsuba(desc, exr, seed)
    return render_cycles(desc, exr, seed)


def render_settings(renderer: str, mode: str) -> dict:
    return {"povray": pov_settings, "cycles": cycles_settings, THIRD: mitsuba_settings}[renderer](mode)


def renderer_version(renderer: str) -> str:
    if renderer == THIRD:
        try:
            import mitsuba
        except ImportError:
            return "not installed"
        return f"Mitsuba {mitsuba.__version__} (scalar_rgb)"
    cmd = ["povray", "--version"] if renderer == "povray" else ["blender", "-b", "--factory-startup", "--version"]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True)
        text = res.stdout + res.stderr
    except OSError:
        return "not installed"
    for line in text.splitlines():
        if line.startswith(("POV-Ray 3", "Blender 3", "Blender 4")):
            return line.strip()
    return "unknown"


# -- the camera model --------------------------------------------------------------------------
def photo_seed(name: str) -> int:
    return (SEED * 7919 + zlib.crc32(name.encode())) % 2**31


def camera_model(name: str, index: int, tones: tuple[str, ...] = TONES) -> dict:
    """The seeded camera/post settings of photo `name` (index cycles the tone curves `tones`)."""
    import numpy as np

    rng = np.random.default_rng(photo_seed(name))
    ev = rng.uniform(-0.6, 0.4)
    wb = [rng.uniform(0.85, 1.15), 1.0, rng.uniform(0.85, 1.15)]
    gamma = rng.uniform(1.6, 2.4)
    look = ("None", "Medium High Contrast", "Medium Low Contrast")[rng.integers(3)]
    blur = 0.0 if rng.random() < 0.25 else rng.uniform(0.3, 1.5)
    vignetting = rng.uniform(0.0, 0.35)
    shot, read = rng.uniform(0.0, 8e-4), rng.uniform(5e-4, 4e-3)
    noise_seed = int(rng.integers(2**31))
    fmt = ("jpeg420", "jpeg444", "png")[rng.choice(3, p=[0.5, 0.3, 0.2])]
    quality = int(rng.integers(50, 96))
    tone = tones[index % len(tones)]
    model = {
        "exposure_ev": round(ev, 3),
        "white_balance": [round(g, 3) for g in wb],
        "blur_sigma_px": round(blur, 3),
        "vignetting": round(vignetting, 3),
        "noise_shot": round(shot, 6),
        "noise_read": round(read, 5),
        "noise_seed": noise_seed,
        "tone": tone,
    }
    if tone == "gamma":
        model["gamma"] = round(gamma, 3)
    if tone == "filmic":
        model["filmic_look"] = look
    model["format"] = "png" if fmt == "png" else "jpeg"
    if fmt != "png":
        model["jpeg_quality"] = quality
        model["jpeg_chroma"] = "4:2:0" if fmt == "jpeg420" else "4:4:4"
    return model


CAMERA_MODEL_DOC = {
    "order": "linear render -> exposure -> white balance -> lens blur -> vignetting -> sensor noise -> tone curve -> 8 bit -> file",
    "exposure_ev": "multiply by 2**exposure_ev",
    "white_balance": "per-channel gains R, G, B",
    "blur_sigma_px": "Gaussian lens blur, sigma in pixels (0: none), edges extended",
    "vignetting": "gain 1 - vignetting * (r / r_corner)**2, r from the image centre",
    "noise_shot, noise_read": "Gaussian noise of variance noise_shot * I + noise_read**2 in linear light (I the exposed value, 1 = white)",
    "tone": "srgb: the sRGB curve; gamma: I**(1/gamma); filmic: Blender 3.4's Filmic view transform with filmic_look (OCIO, sRGB display); "
            "aces: x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14) (Narkowicz 2015), then the sRGB curve",
    "format": "png, or jpeg with jpeg_quality and jpeg_chroma (Pillow; 4:2:0 is its default subsampling)",
}


def develop(linear, model: dict):
    """Apply the camera model up to the tone curve: a linear image, exposed, balanced,
    blurred, vignetted and noisy."""
    import numpy as np
    from scipy.ndimage import gaussian_filter

    x = linear * 2.0 ** model["exposure_ev"] * np.asarray(model["white_balance"])
    if model["blur_sigma_px"] > 0:
        x = np.stack([gaussian_filter(x[..., c], model["blur_sigma_px"], mode="nearest") for c in range(3)], -1)
    h, w, _ = x.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx + 0.5 - w / 2) ** 2 + (yy + 0.5 - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    x = x * (1 - model["vignetting"] * r2)[..., None]
    rng = np.random.default_rng(model["noise_seed"])
    sigma = np.sqrt(model["noise_shot"] * np.maximum(x, 0) + model["noise_read"] ** 2)
    return x + sigma * rng.standard_normal(x.shape)


def tone(x, model: dict):
    """sRGB, plain-gamma or ACES-fit tone curve to 0..1 (Filmic is done by Blender, see `filmic_batch`)."""
    import numpy as np

    if model["tone"] == "aces":
        x = np.maximum(x, 0)
        x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)
    x = np.clip(x, 0, 1)
    if model["tone"] in ("srgb", "aces"):
        return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return x ** (1 / model["gamma"])


def filmic_batch(items: list[dict]) -> None:
    """Apply Blender's Filmic view transform to linear EXR files, writing 8-bit PNGs."""
    if not items:
        return
    job = os.path.join(CACHE, "filmic_job.json")
    with open(job, "w") as f:
        json.dump({"task": "filmic", "items": items}, f)
    run([*NICE, "blender", "-b", "--factory-startup", "-P", SCRIPT, "--", "--blender-job", job], os.path.join(CACHE, "filmic.log"))


def save_photo(path: str, image8, model: dict) -> None:
    from PIL import Image

    im = Image.fromarray(image8, "RGB")
    if model["format"] == "png":
        im.save(path, optimize=True)
    elif model["jpeg_chroma"] == "4:4:4":
        im.save(path, quality=model["jpeg_quality"], subsampling=0)
    else:
        im.save(path, quality=model["jpeg_quality"])  # Pillow's default: 4:2:0


# -- photos, start decks, split ----------------------------------------------------------------
def photo_list() -> list[dict]:
    photos = []
    for deck in DECK_NAMES:
        for renderer in RENDERERS:
            for k in (1, 2) if (deck, renderer) in SECOND_MODEL else (1,):
                photos.append({"name": f"{deck}-{renderer}-{k}", "deck": deck, "renderer": renderer, "model_index": k})
    for i, p in enumerate(photos):
        p["camera"] = camera_model(p["name"], i)
    third = [{"name": f"{deck}-{THIRD}-1", "deck": deck, "renderer": THIRD, "model_index": 1} for deck in DECK_NAMES]
    for i, p in enumerate(third):
        p["camera"] = camera_model(p["name"], i, THIRD_TONES)
    photos += third
    for p in photos:
        p["file"] = p["name"] + (".png" if p["camera"]["format"] == "png" else ".jpg")
    return photos


def holdout(photos: list[dict]) -> set[str]:
    """A third of POV-Ray's and Cycles' photos, one per deck for a seeded order of decks,
    renderers alternating; and every photo of the third renderer."""
    import numpy as np

    n = round(sum(p["renderer"] in RENDERERS for p in photos) / 3)
    order = list(np.random.default_rng(SEED + 1).permutation(len(DECK_NAMES)))
    chosen: list[str] = []
    k = 0
    while len(chosen) < n:
        deck = DECK_NAMES[order[k % len(order)]]
        renderer = RENDERERS[k % 2]
        name = f"{deck}-{renderer}-1"
        if name in chosen:
            name = f"{deck}-{RENDERERS[(k + 1) % 2]}-1"
        chosen.append(name)
        k += 1
    return set(chosen) | {p["name"] for p in photos if p["renderer"] == THIRD}


def start_deck(name: str, deck: str, scene, desc: dict) -> tuple[list[int], list[list[float]]]:
    """Write starts/NAME.dat: every non-floor centre moved by a seeded offset of 5-15 % of its
    radius in a uniform direction. Returns the free sphere indices and the offsets."""
    import numpy as np
    import rtjax

    rng = np.random.default_rng(photo_seed(name) + 1)
    centers = np.asarray(scene.params.centers, np.float64).copy()
    free, offsets = [], []
    for i, s in enumerate(desc["spheres"]):
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        length = rng.uniform(*OFFSET_RANGE) * s["radius"]
        if is_floor(s, desc["median_radius"]):
            continue
        moved = np.round(centers[i] + d * length, 3)
        offsets.append([round(float(c), 3) for c in moved - centers[i]])
        centers[i] = moved
        free.append(i)
    os.makedirs(STARTS, exist_ok=True)
    rtjax.save_deck(
        os.path.join(STARTS, name + ".dat"),
        scene.replace(centers=centers),
        name + "_start.sunimg",
        header=f"Start deck for photos/{name}: decks/{deck}.dat with the centres of spheres {free} moved by 5-15 % of their radii\n"
        "(scripts/make_photos.py); everything else as in the truth deck.",
    )
    return free, offsets


def contact_sheet(photos: list[dict], path: str) -> None:
    from PIL import Image, ImageDraw

    cols, cw, ch = 4, 330, 262
    rows = (len(photos) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * cw, rows * ch), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for k, p in enumerate(photos):
        f = os.path.join(OUT, p["file"])
        if not os.path.exists(f):
            continue
        x, y = (k % cols) * cw + 5, (k // cols) * ch + 5
        sheet.paste(Image.open(f).convert("RGB"), (x, y + 14))
        draw.text((x, y), f"{p['name']} {p['camera']['tone']} [{p['split']}]", fill=(0, 0, 0))
    sheet.save(path)


def make(only: str | None, force: bool) -> None:
    import numpy as np

    os.makedirs(CACHE, exist_ok=True)
    write_ex2s3_copy()
    photos = photo_list()
    held = holdout(photos)
    for p in photos:
        p["truth_deck"] = square_pixel_deck(p["deck"]) if p["renderer"] == THIRD else p["deck"]
    scenes = {p["truth_deck"]: load_scene(os.path.join(DECKS, p["truth_deck"] + ".dat")) for p in photos}
    descs = {name: describe(scene) for name, scene in scenes.items()}
    selected = [p for p in photos if only in (None, p["deck"], p["name"], p["renderer"])]
    if only and not selected:
        raise SystemExit(f"make_photos: --only {only}: no deck, renderer or photo of that name (decks: {', '.join(DECK_NAMES)})")
    require({p["renderer"] for p in selected})

    times = {}
    for deck, renderer, truth in sorted({(p["deck"], p["renderer"], p["truth_deck"]) for p in selected}, key=lambda t: (DECK_NAMES.index(t[0]), t[1])):
        exr = os.path.join(CACHE, "renders", f"{deck}-{renderer}.exr")
        if force or not os.path.exists(exr):
            times[f"{deck}-{renderer}"] = t = render(descs[truth], renderer, exr, photo_seed(deck))
            print(f"rendered {deck} with {renderer}: {t:.1f} s", flush=True)
    if times:
        with open(os.path.join(CACHE, "render_times.json"), "a") as f:
            f.write(json.dumps(times) + "\n")

    filmic, pending = [], []
    for p in selected:
        lin = develop(read_exr(os.path.join(CACHE, "renders", f"{p['deck']}-{p['renderer']}.exr")), p["camera"])
        if p["camera"]["tone"] == "filmic":
            pre = os.path.join(CACHE, "filmic", p["name"] + ".exr")
            os.makedirs(os.path.dirname(pre), exist_ok=True)
            write_exr(pre, lin.astype(np.float32))
            filmic.append({"exr": pre, "png": pre[:-4] + ".png", "look": p["camera"]["filmic_look"]})
            pending.append((p, pre[:-4] + ".png"))
        else:
            save_photo(os.path.join(OUT, p["file"]), np.round(tone(lin, p["camera"]) * 255).astype(np.uint8), p["camera"])
    filmic_batch(filmic)
    for p, png in pending:
        from PIL import Image

        save_photo(os.path.join(OUT, p["file"]), np.asarray(Image.open(png).convert("RGB")), p["camera"])

    entries = []
    for p in photos:
        desc = descs[p["truth_deck"]]
        free, offsets = start_deck(p["name"], p["truth_deck"], scenes[p["truth_deck"]], desc)
        mode_settings = render_settings(p["renderer"], "photo")
        entries.append({
            "name": p["name"], "file": p["file"], "renderer": p["renderer"], "deck": p["deck"],
            "truth": f"decks/{p['truth_deck']}.dat", "start": f"starts/{p['name']}.dat",
            "width": desc["width"], "height": desc["height"], "free": free, "start_offsets": offsets,
            "camera": p["camera"], "render": mode_settings, "render_seed": photo_seed(p["deck"]) if p["renderer"] != "povray" else None,
            "seed": photo_seed(p["name"]), "split": "holdout" if p["name"] in held else "tune",
        })
        p["split"] = entries[-1]["split"]
    manifest_path = os.path.join(OUT, "manifest.json")
    before = json.load(open(manifest_path)).get("renderers", {}) if os.path.exists(manifest_path) else {}
    versions = {r: renderer_version(r) for r in (*RENDERERS, THIRD)}
    manifest = {
        "about": "Photo-like images of deck scenes made by POV-Ray, Blender Cycles and Mitsuba 3, not by rtjax (scripts/make_photos.py). "
                 "Paths are relative to this file's folder. Sphere indices count from 0 in deck order.",
        # A renderer not installed now keeps the version its photos were made with.
        "renderers": {r: before.get(r, v) if v == "not installed" else v for r, v in versions.items()},
        "camera_model": CAMERA_MODEL_DOC,
        "start_offsets": f"free spheres' centres moved by {OFFSET_RANGE[0]:g}-{OFFSET_RANGE[1]:g} of their radius, uniform direction; "
                         f"spheres larger than {FLOOR_FACTOR:g} x the median radius (floors) stay",
        "split_rule": "a third of POV-Ray's and Cycles' photos held out: one photo (camera model 1) per deck, decks in a seeded order, "
                      f"renderers alternating; every {THIRD} photo held out (a renderer the fitting was never tuned on)",
        "photos": entries,
    }
    text = json.dumps(manifest, indent=1)
    text = re.sub(r"\[\s+([^\[\]{}]*?)\s+\]", lambda m: "[" + re.sub(r",\s+", ", ", m.group(1)) + "]", text)  # short lists on one line
    with open(manifest_path, "w") as f:
        f.write(text + "\n")
    contact_sheet(photos, os.path.join(CACHE, "contact_sheet.png"))
    print(f"wrote {len(selected)} photos, {len(entries)} manifest entries; contact sheet {os.path.join(CACHE, 'contact_sheet.png')}")


def require(renderers: set[str]) -> None:
    """Stop with the install command when a renderer that is needed is missing."""
    for renderer, tool in (("povray", "povray"), ("cycles", "blender")):
        if renderer in renderers and shutil.which(tool) is None:
            raise SystemExit(f"make_photos: {tool} not found; install it with: apt-get install -y povray blender")
    if THIRD in renderers and renderer_version(THIRD) == "not installed":
        raise SystemExit("make_photos: mitsuba not found; install it with: pip install mitsuba")


# -- the geometry check ------------------------------------------------------------------------
CHECKS = {
    # name: (eye, refp, (ha, va), width, spheres as (screen x, screen y in half extents, distance factor, radius))
    "oblique": ((100, 150, 80), (0, 0, 0), (40, 30), 320, ((0.0, 0.0, 1.0, 20), (-0.72, 0.55, 0.9, 12), (0.62, -0.66, 1.25, 16))),
    "straight_down": ((0, 0, 200), (0, 0, 0), (50, 36), 240, ((0.1, 0.05, 1.0, 18), (-0.7, 0.6, 0.95, 12), (0.65, -0.5, 1.05, 14))),
    "wide_low": ((-60, -20, 30), (10, 30, 5), (70, 50), 300, ((0.0, 0.2, 1.0, 8), (-0.8, -0.6, 0.7, 6), (0.75, 0.7, 1.6, 12))),
}


def check_deck(name: str, square: bool = False) -> str:
    """A deck of three white-lit spheres (pure red, green, blue at ambient 1) for the check;
    `square`: va set for square pixels (Mitsuba's camera)."""
    import numpy as np
    from rtjax.camera import image_height

    eye, refp, (ha, va), width, spheres = CHECKS[name]
    if square:
        va = square_va(ha, width, image_height(width, ha, va))
    w, u, v = camera_basis(eye, refp)
    dist = np.linalg.norm(np.subtract(refp, eye))
    th, tv = math.tan(math.radians(ha) / 2), math.tan(math.radians(va) / 2)
    lines = [f"# geometry check deck {name} (scripts/make_photos.py --check-geometry)"]
    for k, (sx, sy, f, r) in enumerate(spheres):
        c = np.asarray(eye) + f * dist * (w + sx * th * u + sy * tv * v)
        lines += [f"sphe {c[0]:.3f} {c[1]:.3f} {c[2]:.3f} {r}", "opaq " + " ".join("1" if j == k else "0" for j in range(3)) + " 0 1"]
    lines += ["plig 0 0 1 255 255 255", "back 0 0 0", "elig 1", "eyep %g %g %g" % eye, "refp %g %g %g" % refp, f"vang {ha:.10g} {va:.10g}", f"size {width}", f"rend {name}.sunimg", "quit"]
    return "\n".join(lines) + "\n"


def silhouette_stats(ref, img) -> list[dict]:
    """Per channel (sphere): centroid distance (px) and IoU of the 0.5 masks."""
    import numpy as np

    h, w, _ = ref.shape
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    out = []
    for c in range(3):
        a, b = np.clip(ref[..., c], 0, 1), np.clip(img[..., c], 0, 1)
        ca = np.array([(a * xx).sum(), (a * yy).sum()]) / a.sum()
        cb = np.array([(b * xx).sum(), (b * yy).sum()]) / b.sum()
        ma, mb = a > 0.5, b > 0.5
        out.append({"sphere": c, "diameter_px": round(float(2 * math.sqrt(a.sum() / math.pi)), 1), "centroid_dx": round(float(cb[0] - ca[0]), 3),
                    "centroid_dy": round(float(cb[1] - ca[1]), 3), "centroid_px": round(float(np.linalg.norm(cb - ca)), 3),
                    "iou": round(float((ma & mb).sum() / (ma | mb).sum()), 4), "area_ratio": round(float(b.sum() / a.sum()), 4)})
    return out


def check_geometry(renderers: tuple[str, ...]) -> bool:
    import numpy as np
    import rtjax

    require(set(renderers))
    folder = os.path.join(CACHE, "geometry")
    os.makedirs(folder, exist_ok=True)
    results, ok = {}, True
    for name in CHECKS:
        for renderer in renderers:
            square = renderer == THIRD
            text = check_deck(name, square)
            deck = name + ("-square" if square else "")
            with open(os.path.join(folder, deck + ".dat"), "w") as f:
                f.write(text)
            scene = rtjax.parse_deck(text, deck + ".dat").frames[0].scene
            ref = np.asarray(rtjax.render(scene, spp=8), np.float64) / 255
            exr = os.path.join(folder, f"{name}-{renderer}.exr")
            render(describe(scene, "mask"), renderer, exr, 1)
            stats = silhouette_stats(ref, read_exr(exr))
            results[f"{name}/{renderer}"] = stats
            for s in stats:
                good = s["centroid_px"] < 0.3 and s["iou"] > 0.97
                ok &= good
                print(f"{name:14s} {renderer:7s} {scene.structure.width}x{scene.structure.height} sphere {s['sphere']} d={s['diameter_px']:6.1f}px "
                      f"centroid off {s['centroid_px']:.3f}px ({s['centroid_dx']:+.3f}, {s['centroid_dy']:+.3f})  IoU {s['iou']:.4f}  "
                      f"area {s['area_ratio']:.4f}  {'ok' if good else 'FAIL'}")
    with open(os.path.join(folder, "results.json"), "w") as f:
        json.dump(results, f, indent=1)
    print("geometry check: " + ("all silhouettes agree (centroid < 0.3 px, IoU > 0.97)" if ok else "FAILED"))
    return ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", help="one deck name or one photo name")
    ap.add_argument("--force", action="store_true", help="render again even where a cached render exists")
    ap.add_argument("--check-geometry", action="store_true", help="compare silhouettes with rtjax and exit")
    ap.add_argument("--renderers", default=",".join((*RENDERERS, THIRD)), help="with --check-geometry: the renderers to check")
    args = ap.parse_args(argv)
    if args.check_geometry:
        return 0 if check_geometry(tuple(args.renderers.split(","))) else 1
    make(args.only, args.force)
    return 0


if __name__ == "__main__":
    if "--blender-job" in sys.argv:
        blender_main(sys.argv[sys.argv.index("--blender-job") + 1])
    else:
        sys.exit(main())
