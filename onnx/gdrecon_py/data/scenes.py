"""Procedural scene family for gdrecon's data (Mitsuba 3 built-in shapes, materials, textures).

Every scene is a function ``build(W, H, rng)`` returning a Mitsuba scene *dict* without sensor
film settings (render.py adds the film). ``rng is None`` gives the *base* scene (used for
validation and the bundled sample); a ``numpy.random.Generator`` gives a *perturbed* variant
(materials, colours, lights and camera all vary; used for training only).

Nothing is downloaded: procedural textures are numpy arrays handed to a ``bitmap`` texture.
Call ``mitsuba.set_variant`` before building (render.py does).
"""
from __future__ import annotations

import colorsys
import math

import numpy as np

import mitsuba as mi

# --------------------------------------------------------------------------------------------
# small helpers


def T():
    return mi.ScalarTransform4f()


def u(rng, base, lo, hi):
    """Base value, or a uniform draw in [lo, hi] when perturbing."""
    return base if rng is None else float(rng.uniform(lo, hi))


def choice(rng, base, options):
    return base if rng is None else options[int(rng.integers(len(options)))]


def rgb(v):
    return {"type": "rgb", "value": [float(c) for c in v]}


def colour(rng, base, sat=(0.2, 0.9), val=(0.15, 0.8)):
    """Base colour, or a random colour (hue uniform, saturation/value in the given ranges)."""
    if rng is None:
        return list(base)
    h = rng.uniform(0, 1)
    return list(colorsys.hsv_to_rgb(h, rng.uniform(*sat), rng.uniform(*val)))


def tint(rng, base, amount=0.25):
    """Multiply a base colour by a random near-white tint (light colour temperature etc.)."""
    if rng is None:
        return list(base)
    t = 1.0 + rng.uniform(-amount, amount, 3)
    return [float(b * c) for b, c in zip(base, t)]


def tex(c):
    """A texture dict as is, or an RGB constant."""
    return c if isinstance(c, dict) else rgb(c)


def diffuse(c):
    return {"type": "diffuse", "reflectance": tex(c)}


def twosided(b):
    return {"type": "twosided", "material": b}


def sensor(origin, target, fov, up=(0, 1, 0)):
    return {
        "type": "perspective",
        "fov": float(fov),
        "fov_axis": "x",
        "to_world": T().look_at(origin=list(origin), target=list(target), up=list(up)),
    }


def orbit(rng, origin, target, yaw=12.0, pitch=6.0, dist=0.12):
    """Base camera origin, or the origin rotated around target (yaw about +y, pitch) and moved
    along the view axis. |yaw| is at least 2 degrees so a perturbed camera never equals base."""
    if rng is None:
        return list(origin)
    o = np.array(origin, float)
    t = np.array(target, float)
    d = o - t
    a = math.radians(rng.uniform(2.0, yaw) * rng.choice([-1, 1]))
    c, s = math.cos(a), math.sin(a)
    d = np.array([c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]])
    r = np.linalg.norm(d)
    el = math.asin(d[1] / r) + math.radians(rng.uniform(-pitch, pitch))
    az = math.atan2(d[0], d[2])
    r *= 1.0 + rng.uniform(-dist, dist)
    d = r * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    return list(t + d)


def rect(center, normal, size_u, size_v, bsdf, rot=0.0, emitter=None):
    """Rectangle of half-extent (size_u, size_v) centred at `center`, facing `normal`."""
    n = np.array(normal, float)
    n /= np.linalg.norm(n)
    up = [0, 1, 0] if abs(n[1]) < 0.9 else [0, 0, 1]
    c = np.array(center, float)
    m = T().look_at(origin=list(c), target=list(c + n), up=up)
    m = m.rotate([0, 0, 1], rot).scale([size_u, size_v, 1])
    d = {"type": "rectangle", "to_world": m, "bsdf": bsdf}
    if emitter is not None:
        d["emitter"] = emitter
    return d


def area(radiance):
    return {"type": "area", "radiance": rgb(radiance)}


def box(center, half, bsdf, yaw=0.0):
    return {
        "type": "cube",
        "to_world": T().translate(list(center)).rotate([0, 1, 0], yaw).scale(list(half)),
        "bsdf": bsdf,
    }


def sphere(center, radius, bsdf, emitter=None):
    d = {"type": "sphere", "center": [float(c) for c in center], "radius": float(radius), "bsdf": bsdf}
    if emitter is not None:
        d["emitter"] = emitter
    return d


def checker(c0, c1, scale):
    return {
        "type": "checkerboard",
        "color0": rgb(c0),
        "color1": rgb(c1),
        "to_uv": T().scale([scale, scale, 1]),
    }


def base_dict(integrator_depth=8):
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": integrator_depth},
    }


METALS = ["Au", "Cu", "Ag", "Al", "Cr", "W", "Ni_palik", "Rh", "Ir", "Mo", "TiN"]

# --------------------------------------------------------------------------------------------
# scenes


def cornell(W, H, rng=None):
    """Diffuse interior: Cornell-like box, ceiling area light, two diffuse blocks."""
    s = base_dict()
    white = colour(rng, [0.73, 0.73, 0.73], sat=(0.0, 0.15), val=(0.5, 0.8))
    left = colour(rng, [0.63, 0.065, 0.05])
    right = colour(rng, [0.14, 0.45, 0.091])
    # closed box x, y in [-1, 1], z in [-1, 4]; the camera sits inside, near the front wall
    s["sensor"] = sensor(orbit(rng, [0, 0.2, 3.6], [0, -0.3, 0], yaw=6, pitch=4, dist=0.05),
                         [0, -0.3, 0], u(rng, 60.0, 54.0, 66.0))
    s["floor"] = rect([0, -1, 1.5], [0, 1, 0], 1, 2.5, diffuse(white))
    s["ceiling"] = rect([0, 1, 1.5], [0, -1, 0], 1, 2.5, diffuse(white))
    s["back"] = rect([0, 0, -1], [0, 0, 1], 1, 1, diffuse(white))
    s["front"] = rect([0, 0, 4], [0, 0, -1], 1, 1, diffuse(white))
    s["left"] = rect([-1, 0, 1.5], [1, 0, 0], 2.5, 1, diffuse(left))
    s["right"] = rect([1, 0, 1.5], [-1, 0, 0], 2.5, 1, diffuse(right))
    lx, lz = u(rng, 0.0, -0.4, 0.4), u(rng, 0.0, -0.4, 0.4)
    lsize = u(rng, 0.25, 0.12, 0.4)
    power = u(rng, 17.0, 10.0, 26.0) * (0.25 / lsize) ** 2 * 1.6
    s["light"] = rect([lx, 0.998, lz], [0, -1, 0], lsize, lsize, diffuse([0, 0, 0]),
                      emitter=area(tint(rng, [power, power * 0.75, power * 0.45], 0.2)))
    blk = colour(rng, [0.73, 0.73, 0.73], sat=(0.0, 0.6), val=(0.3, 0.8))
    s["tall"] = box([u(rng, -0.33, -0.5, -0.1), -0.4, u(rng, -0.3, -0.5, 0.0)], [0.3, 0.6, 0.3],
                    diffuse(blk), yaw=u(rng, 18.0, -40, 40))
    s["short"] = box([u(rng, 0.35, 0.15, 0.55), -0.7, u(rng, 0.3, 0.0, 0.5)], [0.3, 0.3, 0.3],
                     diffuse(blk), yaw=u(rng, -17.0, -40, 40))
    return s


def metals(W, H, rng=None):
    """Glossy and rough metals: conductor spheres and a rough conductor block, area light + sky."""
    s = base_dict()
    s["sensor"] = sensor(orbit(rng, [0, 1.6, 5.2], [0, 0.45, 0]), [0, 0.45, 0], u(rng, 45.0, 38, 52))
    s["floor"] = rect([0, 0, 0], [0, 1, 0], 8, 8, diffuse(checker(
        colour(rng, [0.55, 0.55, 0.55], sat=(0, 0.3), val=(0.3, 0.7)),
        colour(rng, [0.25, 0.25, 0.3], sat=(0, 0.3), val=(0.1, 0.4)), u(rng, 10.0, 6, 16))))
    s["back"] = rect([0, 2, -3], [0, 0, 1], 8, 3, diffuse(colour(rng, [0.5, 0.45, 0.4])))
    mats = [choice(rng, m, METALS) for m in ["Au", "Cu", "Al"]]
    alphas = [u(rng, a, 0.01, 0.45) for a in [0.02, 0.12, 0.35]]
    xs = [-1.55, 0.0, 1.55]
    for i, (m, a, x) in enumerate(zip(mats, alphas, xs)):
        r = u(rng, 0.7, 0.5, 0.8)
        s[f"sphere{i}"] = sphere([x + u(rng, 0, -0.2, 0.2), r, u(rng, 0, -0.4, 0.4)], r,
                                 {"type": "roughconductor", "material": m, "alpha": a,
                                  "distribution": "ggx"})
    s["block"] = box([u(rng, 2.6, 2.2, 2.9), 0.35, u(rng, -1.2, -1.6, -0.8)], [0.35, 0.35, 0.35],
                     {"type": "roughconductor", "material": choice(rng, "Cr", METALS),
                      "alpha_u": u(rng, 0.05, 0.02, 0.2), "alpha_v": u(rng, 0.3, 0.1, 0.5)},
                     yaw=u(rng, 30, 0, 90))
    p = u(rng, 12.0, 6.0, 20.0)
    s["light"] = rect([u(rng, -1.5, -2.5, 2.5), 3.5, u(rng, 1.5, 0.5, 2.5)], [0.2, -1, -0.3], 1.0, 0.6,
                      diffuse([0, 0, 0]), emitter=area(tint(rng, [p, p, p * 0.9])))
    e = u(rng, 0.35, 0.15, 0.6)
    s["env"] = {"type": "constant", "radiance": rgb(tint(rng, [e * 0.8, e * 0.9, e * 1.1], 0.3))}
    return s


def glass(W, H, rng=None):
    """Dielectrics with caustics: smooth glass sphere, rough glass block, water-like slab, small
    bright spherical light."""
    s = base_dict(integrator_depth=12)
    s["sensor"] = sensor(orbit(rng, [0, 2.4, 5.0], [0, 0.5, 0]), [0, 0.5, 0], u(rng, 42.0, 36, 50))
    s["floor"] = rect([0, 0, 0], [0, 1, 0], 6, 6, diffuse(colour(rng, [0.7, 0.7, 0.68], sat=(0, 0.2), val=(0.5, 0.85))))
    s["back"] = rect([0, 2.5, -2.5], [0, 0, 1], 6, 2.5, diffuse(colour(rng, [0.4, 0.45, 0.55])))
    ior = u(rng, 1.5, 1.3, 1.8)
    s["ball"] = sphere([u(rng, -0.8, -1.2, -0.4), 0.75, u(rng, 0.2, -0.2, 0.6)], 0.75,
                       {"type": "dielectric", "int_ior": ior, "ext_ior": 1.0,
                        "specular_transmittance": rgb([1, 1, 1] if rng is None else 1 - rng.uniform(0, 0.25, 3))})
    s["block"] = box([u(rng, 1.0, 0.7, 1.4), 0.5, u(rng, -0.3, -0.7, 0.1)], [0.45, 0.5, 0.45],
                     {"type": "roughdielectric", "int_ior": u(rng, 1.33, 1.3, 1.7),
                      "alpha": u(rng, 0.1, 0.03, 0.3),
                      "specular_transmittance": rgb(colour(rng, [0.9, 0.95, 1.0], sat=(0, 0.4), val=(0.8, 1.0)))},
                     yaw=u(rng, 25, -45, 45))
    p = u(rng, 40.0, 25.0, 60.0)
    lp = [u(rng, 0.6, -1.5, 1.5), u(rng, 3.2, 2.6, 3.8), u(rng, 1.2, 0.2, 2.0)]
    s["light"] = sphere(lp, 0.3, diffuse([0, 0, 0]), emitter=area(tint(rng, [p, p * 0.95, p * 0.85])))
    s["env"] = {"type": "constant", "radiance": rgb([0.08, 0.08, 0.09])}
    return s


def _stripes(rng, n=256):
    """Procedural texture (numpy, no download): stripes + value noise, RGB in [0, 1]."""
    r = np.random.default_rng(7) if rng is None else rng
    y, x = np.mgrid[0:n, 0:n] / n
    freq = r.uniform(4, 12)
    ang = r.uniform(0, np.pi)
    st = 0.5 + 0.5 * np.sin(2 * np.pi * freq * (x * np.cos(ang) + y * np.sin(ang)))
    g = r.random((9, 9))
    gi = np.kron(g, np.ones((n // 8 + 1, n // 8 + 1)))[:n, :n]
    c0 = np.array(colorsys.hsv_to_rgb(r.uniform(), 0.7, 0.8))
    c1 = np.array(colorsys.hsv_to_rgb(r.uniform(), 0.5, 0.3))
    t = (0.7 * st + 0.3 * gi)[..., None]
    return (c0 * t + c1 * (1 - t)).astype(np.float32)


def textures(W, H, rng=None):
    """Textures: checkerboard floor and walls, a procedural (numpy) bitmap on a plastic sphere,
    a checkered block; area light + dim environment."""
    s = base_dict()
    s["sensor"] = sensor(orbit(rng, [0.3, 1.4, 4.6], [0, 0.6, 0]), [0, 0.6, 0], u(rng, 48.0, 40, 55))
    s["floor"] = rect([0, 0, 0], [0, 1, 0], 4, 4, diffuse(checker(
        colour(rng, [0.8, 0.8, 0.8], sat=(0, 0.3), val=(0.6, 0.9)),
        colour(rng, [0.1, 0.1, 0.12], sat=(0, 0.5), val=(0.05, 0.3)), u(rng, 8.0, 4, 14))))
    s["back"] = rect([0, 2, -2], [0, 0, 1], 4, 2, diffuse(checker(
        colour(rng, [0.6, 0.3, 0.2]), colour(rng, [0.9, 0.8, 0.5]), u(rng, 12.0, 6, 20))))
    s["left"] = rect([-2.5, 2, 0], [1, 0, 0], 4, 2, diffuse(colour(rng, [0.3, 0.5, 0.6])))
    s["ball"] = sphere([u(rng, -0.6, -0.9, -0.3), 0.7, u(rng, 0.0, -0.3, 0.3)], 0.7,
                       {"type": "plastic", "int_ior": u(rng, 1.5, 1.3, 1.8),
                        "diffuse_reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(_stripes(rng)),
                                                "raw": True}})
    s["block"] = box([u(rng, 1.0, 0.7, 1.3), 0.45, u(rng, 0.3, 0.0, 0.6)], [0.45, 0.45, 0.45],
                     diffuse(checker(colour(rng, [0.9, 0.9, 0.2]), colour(rng, [0.1, 0.3, 0.8]), u(rng, 4.0, 2, 8))),
                     yaw=u(rng, 35, -45, 45))
    s["disk"] = {"type": "disk", "to_world": T().translate([u(rng, 0.3, 0.0, 0.6), 0.01, 1.3])
                 .rotate([1, 0, 0], -90).scale(0.5),
                 "bsdf": {"type": "roughplastic", "alpha": u(rng, 0.15, 0.05, 0.4),
                          "diffuse_reflectance": rgb(colour(rng, [0.7, 0.1, 0.4]))}}
    p = u(rng, 9.0, 5.0, 14.0)
    s["light"] = rect([u(rng, 1.0, -1.5, 1.5), 3.2, u(rng, 1.0, 0.0, 2.0)], [0, -1, 0], 0.8, 0.8,
                      diffuse([0, 0, 0]), emitter=area(tint(rng, [p, p, p])))
    e = u(rng, 0.25, 0.1, 0.45)
    s["env"] = {"type": "constant", "radiance": rgb([e, e, e])}
    return s


def indirect(W, H, rng=None):
    """Indirect-only lighting: a closed room lit by an area light *outside*, through a small
    window in the left wall. Neither the light nor the window is in view: the camera sees a
    directly lit patch and the rest of the room through interreflection only."""
    s = base_dict(integrator_depth=10)
    wall = colour(rng, [0.75, 0.72, 0.68], sat=(0, 0.3), val=(0.55, 0.85))
    # room: x in [-2, 2], y in [0, 2.5], z in [-2, 2]; camera inside near the front wall
    # the camera looks away from the window (>= 43 degrees off-axis, half fov <= 39 degrees)
    cam = orbit(rng, [-1.5, 1.3, 1.8], [1.0, 0.7, -1.2], yaw=8, pitch=4, dist=0.05)
    cam = list(np.clip(cam, [-1.85, 0.3, -1.85], [1.85, 2.2, 1.85]))  # stay inside the room
    s["sensor"] = sensor(cam, [1.0, 0.7, -1.2], u(rng, 70.0, 62, 78))
    s["floor"] = rect([0, 0, 0], [0, 1, 0], 2, 2, diffuse(colour(rng, [0.55, 0.45, 0.35])))
    s["ceiling"] = rect([0, 2.5, 0], [0, -1, 0], 2, 2, diffuse(wall))
    s["back"] = rect([0, 1.25, -2], [0, 0, 1], 2, 1.25, diffuse(wall))
    s["front"] = rect([0, 1.25, 2], [0, 0, -1], 2, 1.25, diffuse(wall))
    s["right"] = rect([2, 1.25, 0], [-1, 0, 0], 2, 1.25, diffuse(colour(rng, [0.35, 0.5, 0.65])))
    # left wall (x = -2) with a window: z in [wz0, wz1], y in [wy0, wy1]
    wc = u(rng, -0.6, -1.2, 0.4)
    hw = u(rng, 0.3, 0.2, 0.45)
    wy0, wy1 = u(rng, 1.2, 0.9, 1.4), u(rng, 1.8, 1.6, 2.1)
    wz0, wz1 = wc - hw, wc + hw
    lw = twosided(diffuse(wall))
    n = [1, 0, 0]
    s["lw_below"] = rect([-2, wy0 / 2, 0], n, 2, wy0 / 2, lw)
    s["lw_above"] = rect([-2, (wy1 + 2.5) / 2, 0], n, 2, (2.5 - wy1) / 2, lw)
    s["lw_back"] = rect([-2, (wy0 + wy1) / 2, (wz0 - 2) / 2], n, (wz0 + 2) / 2, (wy1 - wy0) / 2, lw, rot=0)
    s["lw_front"] = rect([-2, (wy0 + wy1) / 2, (wz1 + 2) / 2], n, (2 - wz1) / 2, (wy1 - wy0) / 2, lw)
    # a table-like block and a sphere inside
    s["table"] = box([u(rng, 0.6, 0.0, 1.2), 0.4, u(rng, -0.8, -1.3, -0.3)], [0.5, 0.4, 0.35],
                     diffuse(colour(rng, [0.6, 0.35, 0.2])), yaw=u(rng, 10, -30, 30))
    s["ball"] = sphere([u(rng, 0.9, 0.5, 1.3), 0.35, u(rng, 0.6, 0.2, 1.0)], 0.35,
                       {"type": "roughplastic", "alpha": 0.2,
                        "diffuse_reflectance": rgb(colour(rng, [0.2, 0.4, 0.8]))})
    # the light: a large panel outside the window, facing it (down-inward like afternoon sky)
    p = u(rng, 60.0, 35.0, 90.0)
    s["light"] = rect([-3.2, wy1 + 0.8, wc], [1, -0.5, 0.1], 1.0, 1.0, diffuse([0, 0, 0]),
                      emitter=area(tint(rng, [p, p * 0.9, p * 0.75], 0.25)))
    return s


def sunsky(W, H, rng=None):
    """Sun and sky: a delta directional sun (hard shadows) plus a Hosek-Wilkie sky (sun part off)
    over a ground plane with blocks, a sphere and a cylinder."""
    s = base_dict()
    s["sensor"] = sensor(orbit(rng, [0, 1.9, 7.0], [0, 0.9, 0], yaw=25), [0, 0.9, 0], u(rng, 50.0, 42, 58))
    s["ground"] = rect([0, 0, 0], [0, 1, 0], 500, 500, diffuse(colour(rng, [0.45, 0.42, 0.36], sat=(0, 0.4), val=(0.3, 0.6))))
    cols = [colour(rng, c) for c in ([0.7, 0.2, 0.15], [0.2, 0.5, 0.7], [0.85, 0.8, 0.7], [0.3, 0.6, 0.2])]
    s["tower"] = box([u(rng, -1.6, -2.2, -1.0), 1.0, u(rng, -0.5, -1.5, 0.5)], [0.35, 1.0, 0.35],
                     diffuse(cols[0]), yaw=u(rng, 20, -45, 45))
    s["cube"] = box([u(rng, 1.4, 0.8, 2.0), 0.4, u(rng, 0.6, 0.0, 1.2)], [0.4, 0.4, 0.4],
                    diffuse(cols[1]), yaw=u(rng, -30, -45, 45))
    s["ball"] = sphere([u(rng, 0.0, -0.5, 0.5), 0.55, u(rng, 1.2, 0.6, 1.8)], 0.55, diffuse(cols[2]))
    s["pillar"] = {"type": "cylinder", "radius": 0.2, "p0": [0.5, 0, -1.5], "p1": [0.5, 1.6, -1.5],
                   "bsdf": diffuse(cols[3])}
    s["fence"] = box([u(rng, -0.3, -1.0, 0.5), 0.3, -2.6], [2.0, 0.3, 0.05], diffuse(colour(rng, [0.6, 0.6, 0.6])))
    el = math.radians(u(rng, 28.0, 12.0, 60.0))
    az = math.radians(u(rng, 40.0, -80.0, 80.0))
    to_sun = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    irr = u(rng, 3.5, 2.0, 5.0)
    s["sun"] = {"type": "directional", "direction": [float(-c) for c in to_sun],
                "irradiance": rgb(tint(rng, [irr, irr * 0.92, irr * 0.8], 0.15))}
    # Mitsuba's sky model is z-up: rotate it to y-up (sun_direction stays in world space)
    s["sky"] = {"type": "sunsky", "to_world": T().rotate([1, 0, 0], -90),
                "sun_direction": [float(c) for c in to_sun], "sun_scale": 0.0,
                "sky_scale": u(rng, 1.0, 0.6, 1.5), "turbidity": u(rng, 3.0, 2.0, 6.0)}
    return s


SCENES = {
    "cornell": cornell,
    "metals": metals,
    "glass": glass,
    "textures": textures,
    "indirect": indirect,
    "sunsky": sunsky,
}
