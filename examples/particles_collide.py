"""Particles falling onto a fused surface: ``kernels.SDFField`` inside someone else's Taichi code.

The example fuses the built-in tabletop scene (bftaichi/synthetic.py: a 1 x 1 m table slab with
its top at z = 0, a sphere, a turned box, a cylinder and a torus on it) with bftaichi's own
pipeline, loads the posterior from ``band.npz`` and hands it to :class:`kernels.SDFField`. Its
own kernel, :meth:`Particles.step`, then drops a few thousand particles (spheres of radius
``radius_m``) from above the table and collides them with the fused surface through the
field's ``@ti.func`` accessors.

Step (symplectic Euler, dt seconds, gravity ``g = (0, 0, -9.81)`` m/s^2), per particle:

1. ``v += dt g``, then ``x += dt v`` (the new velocity moves the particle).
2. ``(d, n, sigma, observed) = scene.query(x)``. If ``observed`` and ``d < r``: push the particle
   out along the normal to ``d = r`` (``x += (r - d) n``; the SDF is a distance, so this is the
   contact's penetration depth), and if it moves into the surface (``v_n = v . n < 0``) reflect
   the normal velocity with restitution ``e``: ``v -= (1 + e) v_n n``, and apply Coulomb
   friction: the tangential velocity ``v_t`` loses ``min(|v_t|, mu (1 + e) |v_n|)`` (the
   friction impulse is at most ``mu`` times the normal one). Without friction, particles
   landing on a slightly tilted normal would slide forever and drift off the table.
3. ``e = e0 exp(-sigma / sigma_ref)``: the posterior standard deviation of the SDF at the contact
   damps the bounce.

Why uncertainty matters to a simulation: a fused surface is an estimate. Where the cameras saw
the surface well (sigma small, millimetres) its position and normal are trustworthy and a
crisp elastic bounce is the right response; where it was seen badly (grazing views, few frames,
sigma a sizeable part of a voxel) the true surface may be centimetres away and its normal
tilted, so a full-energy bounce along a wrong normal throws particles in wrong directions and
amplifies the error. Damping the bounce by the uncertainty keeps a simulated robot or particle
from trusting geometry the sensor never confirmed (the same idea as inflating obstacles by
their uncertainty in planning). Where nothing was observed (``observed = 0``) there is no
collision at all: particles fall through holes in the scan, which shows the holes instead of
inventing surface.

The analytic version (:class:`TabletopSDF`) runs the same step kernel on the exact SDF of the
same primitives (union = minimum of exact primitive SDFs; gradient by central differences,
``sigma = 0``): the reference for the timing of ``tools/bench_embed.py`` and for where the
particles should come to rest.

Run: ``python examples/particles_collide.py --particles 2000 --steps 50``.
"""

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import taichi as ti

import bftaichi as bf
import kernels
from bftaichi.posterior import Posterior

#: ``--set`` overrides of the fused scene: the default tabletop at 96x72 pixels (the 320x240
#: Kinect intrinsics scaled by 0.3), 8 views, 3 cm voxels, 6 cm observation truncation; metrics
#: on few samples and no plots or preview (a ~3 s run).
SCENE_SETS = (
    "synthetic.mesh=tabletop",
    "synthetic.width=96", "synthetic.height=72",
    "synthetic.fx=78.75", "synthetic.fy=78.75", "synthetic.cx=47.5", "synthetic.cy=35.5",
    "synthetic.n_views=8",
    "tsdf.voxel_size_m=0.03", "tsdf.trunc_m=0.06",
    "eval.n_samples=1000", "run.plots=false", "run.preview=false",
)

GRAVITY = (0.0, 0.0, -9.81)  # m/s^2, world z up (DESIGN.md 2)
RADIUS_M = 0.01  # particle radius
DT_S = 0.004  # time step: at the ~3 m/s of a 0.5 m fall a particle moves 1.2 cm per step,
#               less than the band's half thickness (alpha tau = 12 cm), so none tunnels
E0 = 0.6  # restitution of a certain surface
MU = 0.3  # Coulomb friction coefficient
SIGMA_REF_M = 0.02  # sigma at which the restitution drops to e0 / e (about the scan's median)
DROP_BOX = ((-0.42, -0.42, 0.25), (0.42, 0.42, 0.55))  # initial positions, metres (above all
#                                                        objects: the tallest is 0.2 m)

# Tabletop primitives (bftaichi/synthetic.py _TABLE_EXTENTS, _TABLE_OBJECTS; each rests on z = 0).
_SLAB_C, _SLAB_H = (0.0, 0.0, -0.02), (0.5, 0.5, 0.02)  # centre, half extents
_SPHERE_C, _SPHERE_R = (-0.22, 0.18, 0.1), 0.1
_BOX_C, _BOX_H, _BOX_YAW = (0.20, 0.20, 0.06), (0.10, 0.075, 0.06), math.radians(30.0)
_CYL_C, _CYL_R, _CYL_H = (-0.20, -0.20, 0.10), 0.06, 0.10  # half height
_TORUS_C, _TORUS_R, _TORUS_r = (0.20, -0.18, 0.03), 0.08, 0.03


@ti.func
def _box_sdf(q, h):
    """Exact SDF of the box |q_a| <= h_a (q in the box frame)."""
    d = ti.abs(q) - h
    return ti.max(d, 0.0).norm() + ti.min(d.max(), 0.0)


@ti.data_oriented
class TabletopSDF:
    """The exact SDF of the tabletop scene with the accessor of :class:`kernels.SDFField` the
    step kernel uses: ``query(p) -> (sdf, normal, sigma, observed)``, f32, world metres.
    Normal: central differences of the SDF (step ``eps_m``), normalised. ``sigma_m``:
    the constant uncertainty reported everywhere (0: certain); observed is always 1."""

    def __init__(self, sigma_m: float = 0.0, eps_m: float = 1e-4):
        self.sigma_m = float(sigma_m)
        self.eps_m = float(eps_m)

    @ti.func
    def sdf(self, p) -> ti.f32:
        """Distance to the union of the five primitives, metres (the minimum of their SDFs:
        exact outside all of them, which is where particles are)."""
        c, s = ti.cos(_BOX_YAW), ti.sin(_BOX_YAW)
        b = p - ti.Vector(_BOX_C)
        q_box = ti.Vector([c * b[0] + s * b[1], -s * b[0] + c * b[1], b[2]])  # R_z(yaw)^T b
        cy = p - ti.Vector(_CYL_C)
        d_cyl = ti.Vector([ti.Vector([cy[0], cy[1]]).norm() - _CYL_R, ti.abs(cy[2]) - _CYL_H])
        to = p - ti.Vector(_TORUS_C)
        d_tor = ti.Vector([ti.Vector([to[0], to[1]]).norm() - _TORUS_R, to[2]]).norm() - _TORUS_r
        d = _box_sdf(p - ti.Vector(_SLAB_C), ti.Vector(_SLAB_H))
        d = ti.min(d, (p - ti.Vector(_SPHERE_C)).norm() - _SPHERE_R)
        d = ti.min(d, _box_sdf(q_box, ti.Vector(_BOX_H)))
        d = ti.min(d, ti.min(d_cyl.max(), 0.0) + ti.max(d_cyl, 0.0).norm())
        return ti.min(d, d_tor)

    @ti.func
    def query(self, p):
        p = ti.cast(p, ti.f32)
        n = ti.Vector([0.0, 0.0, 0.0])
        for a in ti.static(range(3)):
            e = ti.Vector([self.eps_m if a == b else 0.0 for b in ti.static(range(3))])
            n[a] = self.sdf(p + e) - self.sdf(p - e)
        norm = n.norm()
        if norm > 0:
            n /= norm
        return self.sdf(p), n, ti.cast(self.sigma_m, ti.f32), 1


@ti.data_oriented
class Particles:
    """``n`` particles of radius ``radius_m``: positions ``x`` and velocities ``v``
    (ti.Vector fields (n,) of 3 f32, world metres and m/s), dropped at rest from uniform random
    points of ``DROP_BOX`` (numpy generator ``seed``). Place after ti.init."""

    def __init__(self, n: int, radius_m: float = RADIUS_M, seed: int = 0):
        if int(n) < 1:
            raise ValueError(f"n = {n}: need at least one particle")
        self.n = int(n)
        self.radius_m = float(radius_m)
        lo, hi = (np.array(b, np.float32) for b in DROP_BOX)
        self.x0 = np.random.default_rng(seed).uniform(lo, hi, (self.n, 3)).astype(np.float32)
        self.x = ti.Vector.field(3, ti.f32, self.n)
        self.v = ti.Vector.field(3, ti.f32, self.n)
        self.reset()

    def reset(self) -> None:
        """Back to the initial positions, at rest."""
        self.x.from_numpy(self.x0)
        self.v.fill(0.0)

    @ti.kernel
    def step(self, scene: ti.template(), dt: ti.f32, e0: ti.f32, sigma_ref: ti.f32,
             mu: ti.f32):
        """One symplectic Euler step with collisions against ``scene`` (module docstring).
        One thread per particle, no atomics: deterministic."""
        g = ti.Vector(GRAVITY)
        r = self.radius_m
        for i in self.x:
            v = self.v[i] + dt * g
            x = self.x[i] + dt * v
            d, n, sigma, observed = scene.query(x)
            if observed and d < r:
                x += (r - d) * n  # out to the contact distance
                vn = v.dot(n)
                if vn < 0:
                    e = e0 * ti.exp(-sigma / sigma_ref)
                    vt = v - vn * n
                    vt_norm = vt.norm()
                    v -= (1.0 + e) * vn * n  # normal part: -e vn
                    if vt_norm > 0:  # friction impulse <= mu * normal impulse
                        v -= ti.min(vt_norm, -mu * (1.0 + e) * vn) / vt_norm * vt
            self.x[i] = x
            self.v[i] = v

    def run(self, scene, steps: int, dt: float = DT_S, e0: float = E0,
            sigma_ref: float = SIGMA_REF_M, mu: float = MU) -> list[float]:
        """``steps`` steps against ``scene``; the wall time of each step, seconds (the first
        includes compiling the kernel for this scene)."""
        times = []
        for _ in range(int(steps)):
            t = time.perf_counter()
            self.step(scene, dt, e0, sigma_ref, mu)
            ti.sync()
            times.append(time.perf_counter() - t)
        return times


def fuse_scene(out_dir) -> Posterior:
    """Run bftaichi's pipeline on the tabletop of :data:`SCENE_SETS` into ``out_dir``; return
    the posterior of ``band.npz``."""
    cfg = bf.load_config(None, list(SCENE_SETS))
    bf.run(cfg, out_dir, overwrite=True, progress=False)
    return Posterior.load(Path(out_dir) / "band.npz")


def _per_step(times: list[float]) -> float:
    """Mean seconds per step without the first (compiling) step."""
    return float(np.mean(times[1:])) if len(times) > 1 else float(times[0])


def main(n_particles: int = 2000, steps: int = 200, out=None) -> dict:
    """Fuse the scene, drop ``n_particles`` for ``steps`` steps on the fused and on the analytic
    surface, and return::

        {"positions": (n, 3) float32 final positions on the fused surface, metres,
         "positions_analytic": the same on the analytic surface,
         "field": the kernels.SDFField used, "seconds": {"fuse", "field",
         "step_fused", "step_analytic" (per step, compile excluded), "compile_fused",
         "compile_analytic" (first step)}}

    ``out``: folder for the run's outputs (band.npz, meshes, report.json) and
    ``particles.npz``; None: a temporary folder, deleted afterwards.
    """
    bf.init("cpu")  # the embedding program's init (keeps a runtime started before)
    seconds = {}
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(out) if out is not None else Path(tmp)
        t = time.perf_counter()
        post = fuse_scene(run_dir)
        seconds["fuse"] = time.perf_counter() - t
        t = time.perf_counter()
        field = kernels.SDFField.from_posterior(post)
        seconds["field"] = time.perf_counter() - t
        particles = Particles(n_particles)
        result = {"field": field}
        for name, scene in (("fused", field), ("analytic", TabletopSDF())):
            particles.reset()
            times = particles.run(scene, steps)
            seconds[f"compile_{name}"] = times[0]
            seconds[f"step_{name}"] = _per_step(times)
            key = "positions" if name == "fused" else "positions_analytic"
            result[key] = particles.x.to_numpy()
        if out is not None:
            np.savez(run_dir / "particles.npz", positions=result["positions"],
                     positions_analytic=result["positions_analytic"])
    result["seconds"] = seconds
    return result


def _cli() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--particles", type=int, default=2000, help="number of particles")
    parser.add_argument("--steps", type=int, default=200, help=f"time steps of {DT_S} s")
    parser.add_argument("--out", default=None, help="output folder (default: temporary)")
    args = parser.parse_args()
    res = main(args.particles, args.steps, args.out)
    s = res["seconds"]
    for name in ("positions", "positions_analytic"):
        z = res[name][:, 2]
        print(f"{name}: z median {np.median(z):.3f} m, {np.mean(z < 0.02) * 100:.1f} % down on "
              f"the table top (z < 2 cm), {np.mean(z < -0.05) * 100:.1f} % fell off or through")
    print(f"fuse {s['fuse']:.2f} s, SDFField {s['field'] * 1e3:.1f} ms; per step "
          f"fused {s['step_fused'] * 1e3:.3f} ms, analytic {s['step_analytic'] * 1e3:.3f} ms "
          f"(first steps incl. compile {s['compile_fused']:.2f} / {s['compile_analytic']:.2f} s)")


if __name__ == "__main__":
    _cli()
