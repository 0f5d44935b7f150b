"""Independent float64 NumPy reference of the deck contract (docs: shared/spec/DECK.md).

A slow, independent yardstick for the JAX renderer: the tests compare rtjax's images
with it and `rtjax bench` times it. It was written from DECK.md alone and deliberately
shares no code with the rest of ``rtjax`` (its own deck reader, camera, intersection,
shading and texture sampling; textures are read with Pillow): a straightforward,
readable ray tracer in float64 NumPy, vectorised over pixels but otherwise a literal
transcription of the spec. Keep it so: a shared helper would hide a shared mistake.

Usage::

    from rtjax import reference

    frame = reference.parse_deck_text(open("scene.dat").read(), "folder/of/the/deck")[0]
    image = reference.render_reference(frame, depth=10, spp=1)  # float64 (H, W, 3)

API
---
``parse_deck_text(text, folder=".") -> list[Frame]``
    A tiny deck reader (DECK.md section 1). One ``Frame`` per ``rend`` line, a snapshot of the
    state at that line. It does not validate much and its errors are plain
    ``ValueError``s: the real parser is tested elsewhere. ``tmap`` files are read
    (with Pillow, not rtjax's codec) relative to ``folder`` when a frame is rendered;
    a sphere dict may instead carry its texels directly under ``"texels"``.
``image_size(frame) -> (W, H)``
    DECK.md section 2: W = size, H = floor(size * tan(va/2) / tan(ha/2) + 0.5), at least 1.
``camera_basis(frame) -> (w, u, v)``
    Forward, right and screen-up unit vectors (z up; y stands in if w is parallel to z).
``render_reference(frame, depth=10, spp=1) -> np.ndarray``
    float64 (H, W, 3) image, each sample clamped to [0, 255] and averaged over an
    spp x spp grid per pixel; NOT rounded (see ``quantize``).
``quantize(img) -> np.ndarray``
    The file's pixel values: floor(x + 0.5) of the clamped image, as uint8.
``load_texture(path) -> np.ndarray``
    (h, w, 3) float64 texels 0..255, read with Pillow (Sun raster, PNG, ...).
``sample_texture(texels, p) -> np.ndarray``
    DECK.md section 4: the diffuse colour (M, 3) in 0..1 at outward normals p (M, 3).
``refract(d, n, eta) -> (t, tir)``
    Snell refraction of unit directions d at unit normals n facing the incoming ray,
    with relative index eta = n1/n2; where there is total internal reflection t is the
    mirror reflection and tir is True.

Interpretations of the spec (where it is silent)
------------------------------------------------
* ``round`` in H is floor(x + 0.5) (half up, not Python's banker's rounding); H >= 1.
* A ray is spawned only by mirror and transparent hits. The primary ray is segment 0;
  segments 0..depth are traced; a ray spawned by a hit at segment ``depth`` is not
  traced and contributes black (with depth=0 a mirror hit is black, a glass hit keeps
  its specular term with T = black).
* Self-intersection, with no absolute epsilon: a ray that starts on the surface of
  sphere k (a secondary ray or a shadow ray) can only hit k at its far root, and only
  when it points into k (d . outward < 0); pointing outward (or tangent) it cannot hit k.
  Other spheres (and every sphere, for primary rays) count for roots
  t > 1e-9 * scale, where scale = max(max_k |c_k| + r_k, |eye|).
* Shadow rays (toward a parallel light, unbounded) test every sphere; an opaque,
  mirror or textured sphere with any valid root gives S = 0; every transparent sphere
  with a valid root (including k itself when L points into it) multiplies S by kt^2,
  once per sphere, whether the ray crosses one or two of its interfaces.
* Entering a transparent sphere (d . outward < 0) the relative index is 1/n, leaving it
  n; overlapping spheres are not nested media (each interface is air <-> that sphere).
* The ambient term ke*d*L_lambda is summed over lights, independent of N.L and S.
* Textures (section 4): u = atan2(p_y, p_x)/(2 pi) + 1/2, v = arccos(p_z)/pi with p the
  normalised (P - C); bilinear on texel centres ((x + 1/2)/w, (y + 1/2)/h): the
  coordinate x = u*w - 1/2 taken modulo w (columns wrap), y = v*h - 1/2 clamped to
  [0, h - 1] (rows clamp). At an exact pole NumPy's arctan2(0, 0) = 0 gives u = 1/2.
  A textured sphere is opaque for shadows and spawns no ray.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Frame",
    "parse_deck_text",
    "image_size",
    "camera_basis",
    "render_reference",
    "quantize",
    "refract",
    "load_texture",
    "sample_texture",
]

REL_EPS = 1e-9  # relative self-intersection tolerance for "other" spheres


# --------------------------------------------------------------------------------------
# Deck reading (section 1)
# --------------------------------------------------------------------------------------


@dataclass
class Frame:
    """The scene as it stands at one ``rend`` line."""

    spheres: list = field(default_factory=list)  # dicts: center, r, kind, + material
    lights: list = field(default_factory=list)  # (dir as given (3,), rgb (3,))
    back: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ke: float = 0.0
    eye: np.ndarray | None = None
    refp: np.ndarray | None = None
    ha: float | None = None
    va: float | None = None
    size: int | None = None
    output: str | None = None


def _copy_sphere(s):
    return {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in s.items()}


def parse_deck_text(text: str, folder: str = ".") -> list[Frame]:
    """Read a deck; return one Frame per ``rend`` line (section 1 semantics).

    ``tmap`` file names are resolved against ``folder`` (stored as the sphere's "path")."""
    spheres: list[dict] = []
    lights: list[tuple] = []
    back = np.zeros(3)
    ke = 0.0
    eye = refp = None
    ha = va = None
    size = None
    frames: list[Frame] = []

    def nums(args, k, cmd):
        if len(args) != k:
            raise ValueError(f"{cmd} takes {k} numbers, found {len(args)}")
        return [float(a) for a in args]

    for raw in text.splitlines():
        line = raw.split("#", 1)[0].split()
        if not line:
            continue
        cmd, args = line[0], line[1:]
        if cmd == "quit":
            break
        if cmd == "sphe":
            x, y, z, r = nums(args, 4, cmd)
            spheres.append({"center": np.array([x, y, z]), "r": r, "kind": None})
        elif cmd in ("opaq", "mirr", "trpa", "tmap"):
            if not spheres or spheres[-1]["kind"] is not None:
                raise ValueError(f"{cmd} with no sphere awaiting a material")
            s = spheres[-1]
            if cmd == "opaq":
                dr, dg, db, ks, beta = nums(args, 5, cmd)
                s.update(kind="opaq", d=np.array([dr, dg, db]), ks=ks, beta=beta)
            elif cmd == "mirr":
                nums(args, 0, cmd)
                s.update(kind="mirr")
            elif cmd == "trpa":
                kt, n, ks, beta = nums(args, 4, cmd)
                s.update(kind="trpa", kt=kt, n=n, ks=ks, beta=beta)
            else:  # tmap file [ks beta]
                if len(args) not in (1, 3):
                    raise ValueError("tmap takes a file name and optionally ks beta")
                ks, beta = (float(args[1]), float(args[2])) if len(args) == 3 else (0.0, 1.0)
                s.update(kind="tmap", file=args[0], path=os.path.join(folder, args[0]), ks=ks, beta=beta)
        elif cmd == "plig":
            v = nums(args, 6, cmd)
            lights.append((np.array(v[:3]), np.array(v[3:])))
        elif cmd == "back":
            back = np.array(nums(args, 3, cmd))
        elif cmd == "elig":
            (ke,) = nums(args, 1, cmd)
        elif cmd == "eyep":
            eye = np.array(nums(args, 3, cmd))
        elif cmd == "refp":
            refp = np.array(nums(args, 3, cmd))
        elif cmd == "vang":
            ha, va = nums(args, 2, cmd)
        elif cmd == "size":
            (sz,) = nums(args, 1, cmd)
            size = int(sz)
        elif cmd == "rend":
            if len(args) != 1:
                raise ValueError("rend takes one file name")
            if any(s["kind"] is None for s in spheres):
                raise ValueError("a sphere has no material")
            missing = [n for n, v in (("eyep", eye), ("refp", refp), ("vang", ha), ("size", size)) if v is None]
            if missing:
                raise ValueError("rend before " + ", ".join(missing))
            frames.append(
                Frame(
                    spheres=[_copy_sphere(s) for s in spheres],
                    lights=[(d.copy(), c.copy()) for d, c in lights],
                    back=back.copy(),
                    ke=ke,
                    eye=eye.copy(),
                    refp=refp.copy(),
                    ha=ha,
                    va=va,
                    size=size,
                    output=args[0],
                )
            )
        else:
            raise ValueError(f"unknown command {cmd!r}")
    return frames


# --------------------------------------------------------------------------------------
# Camera (section 2)
# --------------------------------------------------------------------------------------


def _normalize(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def image_size(frame: Frame) -> tuple[int, int]:
    """(W, H): W = size, H = floor(size*tan(va/2)/tan(ha/2) + 0.5), at least 1."""
    W = int(frame.size)
    ratio = math.tan(math.radians(frame.va) / 2) / math.tan(math.radians(frame.ha) / 2)
    H = max(1, int(math.floor(W * ratio + 0.5)))
    return W, H


def camera_basis(frame: Frame):
    """Forward w, right u, screen-up v (unit vectors)."""
    w = _normalize(np.asarray(frame.refp, float) - np.asarray(frame.eye, float))
    up = np.array([0.0, 0.0, 1.0])
    c = np.cross(w, up)
    if np.linalg.norm(c) < 1e-12:  # w parallel to z: y stands in for z
        c = np.cross(w, np.array([0.0, 1.0, 0.0]))
    u = _normalize(c)
    v = np.cross(u, w)
    return w, u, v


def directions(frame: Frame, x, y) -> np.ndarray:
    """Unit directions (..., 3) from the eye through image positions (x, y) in pixels,
    broadcast ((i + ½, j + ½) is pixel (i, j)'s centre)."""
    W, H = image_size(frame)
    w, u, v = camera_basis(frame)
    R = np.linalg.norm(np.asarray(frame.refp, float) - np.asarray(frame.eye, float))
    hx = R * math.tan(math.radians(frame.ha) / 2)
    hy = R * math.tan(math.radians(frame.va) / 2)
    sx, sy = np.broadcast_arrays((np.asarray(x) / W) * 2 - 1, 1 - (np.asarray(y) / H) * 2)
    return _normalize(R * w + (sx * hx)[..., None] * u + (sy * hy)[..., None] * v)


# --------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------


def _intersect_all(o, d, src, centers, radii, tmin):
    """Distances to every sphere along rays o + t d (d unit).

    o, d: (M, 3); src: (M,) index of the sphere each ray starts on (-1: none).
    Returns t of shape (M, S), inf where that sphere is not hit.
    """
    f = o[:, None, :] - centers[None, :, :]  # (M, S, 3)
    b = np.einsum("msk,mk->ms", f, d)
    l = f - b[..., None] * d[:, None, :]  # closest-approach offset, careful form
    disc = radii[None, :] ** 2 - np.einsum("msk,msk->ms", l, l)
    hit = disc >= 0
    sq = np.sqrt(np.where(hit, disc, 0.0))
    t_near = -b - sq
    t_far = -b + sq
    t = np.where(t_near > tmin, t_near, np.where(t_far > tmin, t_far, np.inf))
    # the sphere a ray starts on: far root if the ray points into it, else no hit
    own = np.arange(centers.shape[0])[None, :] == src[:, None]
    t_own = np.where(b < 0, t_far, np.inf)  # b = f.d, f is the outward normal * r
    t = np.where(own, t_own, t)
    return np.where(hit, t, np.inf)


# --------------------------------------------------------------------------------------
# Textures (section 4)
# --------------------------------------------------------------------------------------


def load_texture(path: str) -> np.ndarray:
    """(h, w, 3) float64 texels in 0..255, read with Pillow (independent of rtjax)."""
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.float64)


def sample_texture(texels, p):
    """Diffuse colour (M, 3) in 0..1 at outward normals p (M, 3) (normalised here)."""
    texels = np.asarray(texels, float)
    h, w = texels.shape[:2]
    p = _normalize(np.asarray(p, float))
    u = np.arctan2(p[:, 1], p[:, 0]) / (2 * np.pi) + 0.5
    v = np.arccos(np.clip(p[:, 2], -1.0, 1.0)) / np.pi
    xs = np.mod(u * w - 0.5, w)  # in [0, w): columns wrap
    ys = np.clip(v * h - 0.5, 0.0, h - 1.0)  # rows clamp
    c0 = np.minimum(np.floor(xs).astype(int), w - 1)
    r0 = np.floor(ys).astype(int)
    a = xs - c0
    b = ys - r0
    c1 = (c0 + 1) % w
    r1 = np.minimum(r0 + 1, h - 1)
    out = (
        (1 - a)[:, None] * (1 - b)[:, None] * texels[r0, c0]
        + a[:, None] * (1 - b)[:, None] * texels[r0, c1]
        + (1 - a)[:, None] * b[:, None] * texels[r1, c0]
        + a[:, None] * b[:, None] * texels[r1, c1]
    )
    return out / 255.0


def _texels_of(sphere, cache):
    if "texels" in sphere:
        return np.asarray(sphere["texels"], float)
    path = sphere["path"]
    if path not in cache:
        cache[path] = load_texture(path)
    return cache[path]


def refract(d, n, eta):
    """Refract unit directions d (M,3) at unit normals n (M,3) facing the incoming ray.

    eta = n1 / n2 (M,). Returns (t, tir): t unit (M,3); where Snell's law has no
    solution (total internal reflection), t is the reflected direction and tir True.
    """
    cos_i = -np.einsum("mk,mk->m", d, n)
    k = 1.0 - eta**2 * (1.0 - cos_i**2)
    tir = k < 0
    t_refr = eta[:, None] * d + (eta * cos_i - np.sqrt(np.where(tir, 0.0, k)))[:, None] * n
    t_refl = d + 2.0 * cos_i[:, None] * n
    t = np.where(tir[:, None], t_refl, t_refr)
    return _normalize(t), tir


# --------------------------------------------------------------------------------------
# Rendering (section 3)
# --------------------------------------------------------------------------------------


def _trace(frame: Frame, o, d, depth: int):
    """Colour (M, 3) seen along rays o + t d, following section 3."""
    sph = frame.spheres
    S = len(sph)
    M = o.shape[0]
    color = np.zeros((M, 3))
    if S == 0:
        color[:] = frame.back
        return color

    centers = np.array([s["center"] for s in sph], float)
    radii = np.array([s["r"] for s in sph], float)
    kind = np.array([s["kind"] for s in sph])
    is_opaq, is_mirr, is_trpa, is_tmap = kind == "opaq", kind == "mirr", kind == "trpa", kind == "tmap"
    cache: dict = {}
    texels = {i: _texels_of(s, cache) for i, s in enumerate(sph) if s["kind"] == "tmap"}
    dif = np.array([s.get("d", np.zeros(3)) for s in sph], float)
    ks = np.array([s.get("ks", 0.0) for s in sph], float)
    beta = np.array([s.get("beta", 1.0) for s in sph], float)
    kt = np.array([s.get("kt", 0.0) for s in sph], float)
    nidx = np.array([s.get("n", 1.0) for s in sph], float)
    # transmittance of each sphere for shadow rays: kt^2 for glass, 0 otherwise
    shadow_factor = np.where(is_trpa, kt**2, 0.0)

    Ldir = [_normalize(np.asarray(ld, float)) for ld, _ in frame.lights]
    Lrgb = [np.asarray(lc, float) for _, lc in frame.lights]
    ke = float(frame.ke)
    back = np.asarray(frame.back, float)

    scale = max(float(np.max(np.linalg.norm(centers, axis=1) + radii)), float(np.linalg.norm(frame.eye)))
    tmin = REL_EPS * scale

    weight = np.ones(M)  # throughput of the chain (product of kt's)
    alive = np.ones(M, bool)
    src = np.full(M, -1)  # sphere each ray starts on
    o = o.copy()
    d = d.copy()

    for seg in range(depth + 1):
        idx = np.nonzero(alive)[0]
        if idx.size == 0:
            break
        oo, dd, ss, ww = o[idx], d[idx], src[idx], weight[idx]
        t_all = _intersect_all(oo, dd, ss, centers, radii, tmin)
        k = np.argmin(t_all, axis=1)
        t = t_all[np.arange(idx.size), k]
        missed = ~np.isfinite(t)

        # miss: background, the chain ends
        color[idx[missed]] += ww[missed, None] * back
        alive[idx[missed]] = False

        h = ~missed
        hidx, k, t, oo, dd, ww = idx[h], k[h], t[h], oo[h], dd[h], ww[h]
        if hidx.size == 0:
            break
        P = oo + t[:, None] * dd
        outward = _normalize(P - centers[k])
        entering = np.einsum("mk,mk->m", dd, outward) < 0
        N = np.where(entering[:, None], outward, -outward)  # faces the incoming ray
        V = -dd
        # diffuse colour per hit: the sphere's own, or its texture's at the hit
        dif_hit = dif[k]
        for i, tx in texels.items():
            on = k == i
            if np.any(on):
                dif_hit[on] = sample_texture(tx, outward[on])

        # local (direct) lighting, for opaque and transparent hits
        local = np.zeros((hidx.size, 3))
        for Lu, Lc in zip(Ldir, Lrgb):
            Lm = np.broadcast_to(Lu, P.shape)
            NL = np.einsum("mk,mk->m", N, Lm)
            RL = 2.0 * NL[:, None] * N - Lm
            cosg = np.einsum("mk,mk->m", RL, V)
            spec = ks[k] * np.maximum(cosg, 0.0) ** beta[k] * (NL > 0)
            # shadow ray from P toward the light, starting on sphere k
            ts = _intersect_all(P, np.ascontiguousarray(Lm), k, centers, radii, tmin)
            blocked = np.isfinite(ts)
            Svis = np.prod(np.where(blocked, shadow_factor[None, :], 1.0), axis=1)
            op = is_opaq[k] | is_tmap[k]
            diffuse = (1.0 - ke) * np.maximum(NL, 0.0)[:, None] * dif_hit
            opaque_I = ke * dif_hit * Lc + Svis[:, None] * (diffuse * Lc + spec[:, None] * Lc)
            glass_I = Svis[:, None] * spec[:, None] * Lc
            local += np.where(op[:, None], opaque_I, np.where(is_trpa[k][:, None], glass_I, 0.0))
        color[hidx] += ww[:, None] * local

        # spawn at most one further ray
        new_d = np.zeros_like(dd)
        cont = is_mirr[k] | is_trpa[k]
        m = is_mirr[k]
        cos_i = np.einsum("mk,mk->m", dd, N)
        new_d[m] = _normalize(dd[m] - 2.0 * cos_i[m, None] * N[m])
        g = is_trpa[k]
        if np.any(g):
            eta = np.where(entering[g], 1.0 / nidx[k[g]], nidx[k[g]])
            new_d[g], _ = refract(dd[g], N[g], eta)
        new_w = ww * np.where(g, kt[k], 1.0)

        alive[hidx] = cont if seg < depth else False  # beyond depth: black
        o[hidx] = P
        d[hidx] = new_d
        src[hidx] = k
        weight[hidx] = new_w
    return color


def render_reference(frame: Frame, depth: int = 10, spp: int = 1) -> np.ndarray:
    """Render a frame: float64 (H, W, 3), samples clamped to [0, 255] then averaged."""
    W, H = image_size(frame)
    sub = (np.arange(spp) + 0.5) / spp  # sub-sample offsets within a pixel
    across = np.arange(W)[None, :, None, None] + sub[None, None, None, :]
    down = np.arange(H)[:, None, None, None] + sub[None, None, :, None]
    x, y = np.broadcast_arrays(across, down)  # (H, W, spp, spp)
    col = render_positions(frame, np.stack([x.ravel(), y.ravel()], axis=-1), depth)
    return col.reshape(H, W, spp * spp, 3).mean(axis=2)


def render_positions(frame: Frame, xy, depth: int = 10) -> np.ndarray:
    """Colours (K, 3), float64, clamped to [0, 255], through K image positions `xy` (K, 2)
    in pixels: `rtjax.render_samples`'s counterpart, for checks of one box or a few."""
    xy = np.asarray(xy, float)
    d = directions(frame, xy[:, 0], xy[:, 1])
    o = np.broadcast_to(np.asarray(frame.eye, float), d.shape).copy()
    return np.clip(_trace(frame, o, d, depth), 0.0, 255.0)


def quantize(img: np.ndarray) -> np.ndarray:
    """Pixel values as written to a file: clamp, round half up, uint8."""
    return np.floor(np.clip(img, 0.0, 255.0) + 0.5).astype(np.uint8)
