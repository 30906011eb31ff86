"""Write unseen scenes of a stress kind: the same failure class, drawn with parameters from a seed.

    python bench/variant_scenes.py KIND SEED OUT [--resolution 400] [--frames 120]

KIND is ``occluder`` (a small sphere on a loop that a large static box hides from part of the
rig: a wall, a pillar or a long low block, the loop's size, turns, direction, height and the
sphere's radius drawn from SEED) or ``fast`` (a ball that rises out of the floor, flies an arc
within 12-18% of the time range and sinks again, beside a still box) or ``spinning`` (a
checkered or striped sphere that spins on a bouncing or gliding path, and a patterned box that
spins in place, each with its own axis and rate). The scenes are written
like the stress suite's (``nehad synth --stress``: the MuJoCo protocol, label masks), so
``nehad train OUT -o RUN && nehad eval RUN`` scores each object per time quarter. The recipe is
meant to be checked on these, not tuned to them: a new seed is a scene it has not seen.
Prints the drawn parameters.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from nehad.data.synth import Box, Sphere, _axis_angle
from nehad.data.synth_stress import FLOOR, synthesize_stress_scene


def _box_distance(p: np.ndarray, box: Box) -> float:
    """Distance from point `p` to the (solid) oriented box."""
    local = box.rotation.T @ (p - box.centre)
    return float(np.linalg.norm(np.maximum(np.abs(local) - box.half_size, 0.0)))


def _colour(rng) -> tuple[float, float, float]:
    hue = rng.uniform(0, 6)
    c = [max(0.0, min(1.0, abs((hue + k) % 6 - 3) - 1)) for k in (0, 4, 2)]
    return tuple(0.15 + 0.8 * x for x in c)


def occluder_variant(seed: int):
    """A box occluder and a sphere on a loop around it that never touches it."""
    rng = np.random.default_rng([seed, 7919])
    shape = ["wall", "pillar", "block"][rng.integers(3)]
    half = {"wall": [0.06, rng.uniform(0.8, 1.2), rng.uniform(0.5, 0.8)],
            "pillar": [rng.uniform(0.25, 0.4), rng.uniform(0.25, 0.4), rng.uniform(0.6, 0.9)],
            "block": [rng.uniform(0.6, 0.8), rng.uniform(0.15, 0.25), rng.uniform(0.3, 0.4)]}[shape]
    half = np.array(half)
    box = Box(shape, np.array([0.0, 0.0, half[2]]), half,
              _axis_angle([0, 0, 1], rng.uniform(0, math.pi)), _colour(rng))
    colour = _colour(rng)
    while True:
        p = dict(radius=rng.uniform(0.09, 0.13), a=rng.uniform(0.8, 1.4), b=rng.uniform(0.8, 1.5),
                 turns=rng.uniform(0.8, 1.2), direction=float(rng.choice([-1, 1])),
                 phase=rng.uniform(0, 2 * math.pi), z0=rng.uniform(0.25, 0.5),
                 dz=rng.uniform(0.05, 0.25), lobes=int(rng.integers(1, 4)))

        def centre(t, p=p):
            th = p["phase"] + p["direction"] * 2 * math.pi * p["turns"] * t
            return np.array([p["a"] * math.cos(th), p["b"] * math.sin(th),
                             p["z0"] + p["dz"] * math.sin(p["lobes"] * th)])

        if all(_box_distance(centre(t), box) > p["radius"] + 0.05
               for t in np.linspace(0, 1, 400)):
            break
    params = {"occluder": shape, "half_size": half.round(3).tolist(), **{
        k: round(v, 3) if isinstance(v, float) else v for k, v in p.items()}}
    return (lambda t: [FLOOR, box, Sphere("sphere", centre(t), p["radius"], colour)]), params


def fast_variant(seed: int):
    """A ball that is in the air for 12-18% of the time range, beside a still box."""
    rng = np.random.default_rng([seed, 7919])
    start, span = rng.uniform(0.1, 0.75), rng.uniform(0.12, 0.18)
    r = rng.uniform(0.09, 0.15)
    az = rng.uniform(0, 2 * math.pi)
    direction = np.array([math.cos(az), math.sin(az), 0.0])
    side = np.array([-direction[1], direction[0], 0.0]) * rng.uniform(-0.4, 0.4)
    height = rng.uniform(0.8, 1.8)
    half = np.array([rng.uniform(0.15, 0.3), rng.uniform(0.15, 0.3), rng.uniform(0.2, 0.6)])
    box = Box("block", np.array([*(-side[:2] * 1.5 + rng.uniform(-0.3, 0.3, 2)), half[2]]), half,
              _axis_angle([0, 0, 1], rng.uniform(0, math.pi)), _colour(rng))
    colour = _colour(rng)

    def ball(t):
        u = min(max((t - start) / span, 0.0), 1.0)
        below = -(r + 0.3) if u in (0.0, 1.0) else 0.0  # hidden under the floor
        return side + direction * 1.5 * (2 * u - 1) + np.array(
            [0.0, 0.0, below + (r - 0.3) * (1 - 4 * u * (1 - u)) + 4 * height * u * (1 - u)])

    params = {"start": round(start, 3), "span": round(span, 3), "radius": round(r, 3),
              "azimuth": round(az, 3), "height": round(height, 3)}
    return (lambda t: [FLOOR, box, Sphere("ball", ball(t), r, colour)]), params


def spinning_variant(seed: int):
    """A patterned sphere that spins on a path (bouncing or gliding) and a patterned box that
    spins in place clear of it, their patterns, colours, axes and rates drawn from the seed."""
    from nehad.data.synth import Surface

    rng = np.random.default_rng([seed, 7919])
    r = rng.uniform(0.25, 0.4)
    axis = rng.normal(size=3)
    rate = float(rng.choice([-1, 1])) * 2 * math.pi * rng.uniform(1.0, 3.0)
    start, end = rng.uniform(-0.8, 0.8, 2), rng.uniform(-0.8, 0.8, 2)
    bounces, hop = int(rng.integers(0, 4)), rng.uniform(0.3, 0.8)
    sphere_surface = Surface(str(rng.choice(["checker", "stripes"])), _colour(rng),
                             cells=int(rng.integers(3, 6)) * 2)
    colour = _colour(rng)
    half = np.array([rng.uniform(0.2, 0.35), rng.uniform(0.15, 0.3), rng.uniform(0.2, 0.35)])
    box_axis, box_rate = rng.normal(size=3), 2 * math.pi * rng.uniform(0.5, 2.0)
    box_at = np.array([*(-(start + end) / 2 + rng.uniform(-0.2, 0.2, 2)), half[2] + 0.05])
    box_surface = Surface(str(rng.choice(["checker", "stripes"])), _colour(rng),
                          cells=int(rng.integers(3, 7)))
    box_colour = _colour(rng)

    def centre(t):
        xy = start + (end - start) * t
        return np.array([*xy, r + hop * abs(math.sin(math.pi * bounces * t))])

    reach = r + float(np.linalg.norm(half)) + 0.1  # the turning box never meets the sphere
    while not all(np.linalg.norm(centre(t) - box_at) > reach for t in np.linspace(0, 1, 200)):
        box_at = np.array([*rng.uniform(-1.0, 1.0, 2), half[2] + 0.05])

    def objects(t):
        return [FLOOR,
                Sphere("sphere", centre(t), r, colour, rotation=_axis_angle(axis, rate * t),
                       surface=sphere_surface),
                Box("box", box_at, half, _axis_angle(box_axis, box_rate * t), box_colour,
                    surface=box_surface)]

    params = {"radius": round(r, 3), "rate": round(rate, 3), "bounces": bounces,
              "sphere_pattern": sphere_surface.pattern, "cells": sphere_surface.cells,
              "box_rate": round(box_rate, 3), "box_pattern": box_surface.pattern}
    return objects, params


KINDS = {"occluder": occluder_variant, "fast": fast_variant, "spinning": spinning_variant}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("kind", choices=sorted(KINDS))
    ap.add_argument("seed", type=int)
    ap.add_argument("out")
    ap.add_argument("--resolution", type=int, default=400)
    ap.add_argument("--frames", type=int, default=120)
    args = ap.parse_args()
    objects, params = KINDS[args.kind](args.seed)
    print(json.dumps({"kind": args.kind, "seed": args.seed, **params}))
    synthesize_stress_scene(args.out, args.kind, resolution=args.resolution, frames=args.frames,
                            seed=args.seed, objects=objects)


if __name__ == "__main__":
    main()
