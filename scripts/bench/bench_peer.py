#!/usr/bin/env python
"""Side by side with Mitsuba 3 (prbvolpath, path-replay backpropagation): agreement, speed, error against time.

The same scene in both renderers (all parts but `sphere`): a slab box of nearest-filtered voxel grids, HG g = 0.4,
smooth dielectric IOR 1.5, constant environment radiance 1, an orthographic sensor over the top face with one pixel
per texel (our texel sensor). Prints JSON lines (and writes them to --out):

  agreement_grey      grey σ_t (the peer is reliable): per-texel primal z-test (Bonferroni) and per-voxel gradient
                      z-test of a linear objective Σ w·image with fixed random weights, both over independent seeds
  chromatic_bias      chromatic σ_t (the peer's RGB volume sampling is known to be biased here): both renderers
                      against the independent numpy reference tracer (torch_appearance.testing.reference_tracer)
  timing              forward and forward+backward at equal spp after warm-up (the peer JIT-compiles first),
                      medians; ratio_forward and ratio_forward_backward = peer time / our time
  efficiency          RMSE of the primal image and of the gradient against a high-spp reference for a ladder of
                      spp, against wall time, for both renderers (efficiency.png + efficiency.json)
  sphere              a grey heterogeneous grid medium (σ_t 2..12 mm⁻¹, albedo 0.5..0.99, nearest voxels) inside a
                      smooth dielectric sphere (IOR 1.5, R = --sphere-radius) under an orthographic camera: the
                      peer's analytic sphere against our SDFBoundary, the zero set of the trilinear interpolant of
                      exact corner distances, which lies inside the sphere by at most δ = 3h²/(8(R − h√3)).
                      Discretisation bound per pixel (and voxel): the larger change of our image when the sphere is
                      R + δ or R − δ (same seeds). Per-pixel primal z-test (Bonferroni) over independent seeds,
                      raw and beyond that bound, the number of pixels outside bound + noise, the mean relative
                      difference (all sphere pixels; interior pixels ≥ 3δ inside the silhouette; our voxels split
                      to h/2 and h/4, same medium, and the h² extrapolation), the z of a mirrored peer image and of
                      our medium moved by half a voxel (the test resolves orientation and placement) and background
                      pixels (exactly 1 in both: no medium outside the sphere); per-voxel gradient z-test of
                      Σ w·image against the peer with a majorant 1.25 × max σ_t (with the tight majorant its
                      null-collision gradient is biased at the densest voxels: reported, with finite differences
                      as arbiter); forward and forward+backward timing at equal spp like `timing`. One line
                      {"part": "sphere", ...} and sphere.png (ours | Mitsuba | difference) beside --out

Needs the optional peer: `make bench-peer` installs mitsuba==3.5.2 and drjit==0.4.6 into the venv and points
DRJIT_LIBLLVM_PATH at Debian's libLLVM-15 (package libllvm15). The test suite never needs it.
"""
import argparse
import json
import math
import os
import statistics
import sys
import time

import numpy as np
import torch

import torch_appearance as ta
from torch_appearance import io as ta_io


def _load_mitsuba():
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        for cand in ("/lib/x86_64-linux-gnu/libLLVM-15.so.1", "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"):
            if os.path.exists(cand):
                os.environ["DRJIT_LIBLLVM_PATH"] = cand
                break
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:
        sys.exit(f"bench_peer.py: the peer renderer is not installed ({exc}); run `make bench-peer`")
    mi.set_variant("llvm_ad_rgb")
    return mi, dr


mi, dr = None, None
KEY_SIGMA = "slab.interior_medium.sigma_t.data"


# ------------------------------------------------------------------------------------------------ scenes
def make_scene(kind, size, depth, seed=0):
    """(sigma_t, albedo) float32 (3, D, H, W): 'grey' (σ_t equal in R, G, B) or 'chromatic' (ink-like)."""
    g = torch.Generator().manual_seed(seed)
    shape = (depth, size, size)
    if kind == "grey":
        sigma = (2 + 22 * torch.rand(1, *shape, generator=g)).expand(3, *shape).contiguous()
    else:
        base = torch.tensor([2.25, 3.75, 19.0]).view(3, 1, 1, 1)
        sigma = base * (0.5 + torch.rand(3, *shape, generator=g))
    albedo = 0.05 + (0.9997 - 0.05) * torch.rand(3, *shape, generator=g)
    return sigma.float(), albedo.float()


def gridvolume(x, to_world, extra=None):
    """A (3, D, H, W) grid as the peer's nearest-filtered raw gridvolume: the unit cube maps onto ``to_world``."""
    out = {"type": "gridvolume", "data": np.ascontiguousarray(x.numpy().transpose(1, 2, 3, 0)), "raw": True,
           "filter_type": "nearest", "to_world": to_world}
    out.update(extra or {})
    return out


def mitsuba_scene(sigma, albedo, s, spp, max_depth, majorant):
    T = mi.ScalarTransform4f
    _, d, h, w = sigma.shape
    X, Y, Z = w * s, h * s, d * s
    grid_tf = T.scale([X, Y, Z])

    def grid(x, extra=None):
        return gridvolume(x, grid_tf, extra)

    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "prbvolpath", "max_depth": max_depth, "rr_depth": max_depth},
        "sensor": {"type": "orthographic",
                   # orthographic extent is [-1, 1] horizontally and [-1/aspect, 1/aspect] vertically
                   "to_world": T.look_at(origin=[X / 2, Y / 2, Z + 1.0], target=[X / 2, Y / 2, 0.0], up=[0, 1, 0])
                   @ T.scale([X / 2, X / 2, 1]),
                   "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "slab": {"type": "cube", "to_world": T.translate([X / 2, Y / 2, Z / 2]) @ T.scale([X / 2, Y / 2, Z / 2]),
                 "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0},
                 "interior": {"type": "heterogeneous", "sigma_t": grid(sigma, {"max_value": float(majorant)}),
                              "albedo": grid(albedo), "scale": 1.0, "phase": {"type": "hg", "g": 0.4},
                              "sample_emitters": False}},
    })


class Peer:
    """Mitsuba renders in our conventions: image (H, W, 3) with texel [j, i]; gradient (3, D, H, W)."""
    key = KEY_SIGMA
    flip_rows = True  # film rows run top-down, texel rows j run along +y

    def _rows(self, a):
        return a[::-1] if self.flip_rows else a

    def __init__(self, sigma, albedo, s, max_depth):
        self.shape = sigma.shape
        self.scene = mitsuba_scene(sigma, albedo, s, 1, max_depth, float(sigma.max()))
        self.params = mi.traverse(self.scene)

    def forward(self, spp, seed):
        img = mi.render(self.scene, spp=spp, seed=seed)
        return torch.from_numpy(self._rows(np.array(img)).copy())

    def forward_backward(self, spp, seed, weights):
        dr.enable_grad(self.params[self.key])
        self.params.update()
        img = mi.render(self.scene, self.params, spp=spp, seed=seed, seed_grad=seed + 7919)
        w = mi.TensorXf(np.ascontiguousarray(self._rows(weights.numpy())))
        loss = dr.sum(dr.ravel(img * w))
        dr.backward(loss)
        grad = np.array(dr.grad(self.params[self.key]))  # (D, H, W, 3)
        dr.disable_grad(self.params[self.key])
        self.params.update()
        primal = torch.from_numpy(self._rows(np.array(img)).copy())
        return primal, torch.from_numpy(grad.transpose(3, 0, 1, 2).copy())


class Ours:
    def __init__(self, sigma, albedo, s, max_depth):
        self.sigma, self.albedo, self.s, self.max_depth = sigma, albedo, s, max_depth

    def forward(self, spp, seed):
        with torch.no_grad():
            return ta.render_texels(self.sigma, self.albedo, voxel_size=self.s, spp=spp, seed=seed,
                                    max_depth=self.max_depth)

    def forward_backward(self, spp, seed, weights):
        s = self.sigma.clone().requires_grad_()
        img = ta.render_texels(s, self.albedo, voxel_size=self.s, spp=spp, seed=seed, max_depth=self.max_depth)
        (img * weights).sum().backward()
        return img.detach(), s.grad


def seed_stats(fn, k, offset=0):
    xs = torch.stack([fn(offset + i).double() for i in range(k)])
    return xs.mean(0), xs.std(0) / math.sqrt(k)


def zmax(a, sa, b, sb):
    z = (a - b).abs() / (sa ** 2 + sb ** 2).sqrt().clamp_min(1e-30)
    return float(z.max()), z


def bonferroni(n, alpha=1e-3):
    from scipy.stats import norm
    return float(norm.isf(alpha / (2 * n)))


def timed(fn, reps):
    times = []
    for r in range(reps):
        t = time.perf_counter()
        fn(r)
        times.append(time.perf_counter() - t)
    return statistics.median(times)


# ------------------------------------------------------------------------------------------------ sphere
KEY_SPHERE_SIGMA = "sphere.interior_medium.sigma_t.data"
#: The peer's majorant for its gradient: the grid's maximum σ_t times this. With the maximum itself (the slab
#: part's choice, fine for the primal) the densest voxel has null density ≈ 0, and prbvolpath's gradient samples
#: the −∂T/∂σ_t term of a voxel only through its null collisions (probability σ_n/σ_maj): near σ_n = 0 that
#: voxel's gradient is heavy-tailed and in practice biased high (exactly 0 null density: biased).
SPHERE_MAJORANT_MARGIN = 1.25
SE_FLOOR = 1e-6  # float32 resolution of a pixel near 1: background pixels (exactly 1 in both) compare as equal


class SphereSetup:
    """The sphere part's scene: a grey heterogeneous medium in a smooth dielectric sphere, orthographic camera.

    The grid is padded by at least one voxel around the sphere (our SDF must be > 0 on its outer corners); its
    three sides differ (D, H, W) = (n, n + 1, n + 2) and its origin is off zero, so that an axis or placement
    mix-up between the renderers misplaces the medium. Camera: along −z from 5 mm above the centre, up +y, the
    image 10 % wider than the sphere's diameter.
    """

    def __init__(self, radius, s, res, origin=(0.3, -0.4, 0.1)):
        n = math.ceil(2 * radius / s) + 2
        self.shape = (n, n + 1, n + 2)
        self.s, self.radius, self.res, self.origin = s, radius, res, tuple(origin)
        d, h, w = self.shape
        self.centre = tuple(o + k * s / 2 for o, k in zip(origin, (w, h, d)))
        self.eye = (self.centre[0], self.centre[1], self.centre[2] + 5.0)
        self.extent = 2.2 * radius
        # trilinear interpolation error of the sphere's distance function, radially (our surface lies inside)
        self.delta = 3 * s ** 2 / (8 * (radius - s * math.sqrt(3)))

    def medium(self, seed):
        """σ_t grey in [2, 12] mm⁻¹ and albedo per channel in [0.5, 0.99], nearest-filtered voxels, float32."""
        g = torch.Generator().manual_seed(seed)
        sigma = (2 + 10 * torch.rand(1, *self.shape, generator=g)).expand(3, *self.shape).contiguous()
        albedo = 0.5 + 0.49 * torch.rand(3, *self.shape, generator=g)
        return sigma.float(), albedo.float()

    def ours_scene(self, max_depth, radius=None, refine=1, shift=(0.0, 0.0, 0.0)):
        """Our Scene; ``refine`` = f splits each voxel into f³ (the same medium) and samples the SDF at s/f;
        ``shift`` (mm) moves the grid, hence the medium, but not the sphere (a deliberate misplacement)."""
        from torch_appearance.geometry import sphere_sdf
        from torch_appearance.render import ConstantEnvironment, OrthographicCamera, Scene, SDFBoundary
        shape = tuple(k * refine for k in self.shape)
        origin = tuple(o + d for o, d in zip(self.origin, shift))
        sdf = sphere_sdf(shape, self.s / refine, origin, self.centre, radius or self.radius)
        return Scene(voxel_size=self.s / refine, origin=origin, boundary=SDFBoundary(sdf, ior=1.5),
                     sensor=OrthographicCamera(origin=self.eye, target=self.centre, up=(0, 1, 0),
                                               extent_mm=(self.extent, self.extent), resolution=(self.res, self.res)),
                     emitter=ConstantEnvironment(1.0), g=0.4, max_depth=max_depth)

    def pixel_rho(self):
        """(rows, cols) distance (mm) of each pixel centre from the sphere's axis, and the pixel's half-diagonal."""
        p = self.extent / self.res
        c = (torch.arange(self.res, dtype=torch.float64) + 0.5) * p - self.extent / 2
        y, x = torch.meshgrid(-c, c, indexing="ij")  # row 0 is the up (+y) side, column 0 the left (−x) side
        return (x ** 2 + y ** 2).sqrt(), p / math.sqrt(2)


def mitsuba_sphere_scene(su, sigma, albedo, max_depth, majorant):
    """The peer's analytic sphere with the same medium: its gridvolumes cover our grid box, padding included."""
    T = mi.ScalarTransform4f
    d, h, w = su.shape
    grid_tf = T.translate(list(su.origin)) @ T.scale([w * su.s, h * su.s, d * su.s])
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "prbvolpath", "max_depth": max_depth, "rr_depth": max_depth},
        "sensor": {"type": "orthographic",
                   "to_world": T.look_at(origin=list(su.eye), target=list(su.centre), up=[0, 1, 0])
                   @ T.scale([su.extent / 2, su.extent / 2, 1]),
                   "film": {"type": "hdrfilm", "width": su.res, "height": su.res, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "sphere": {"type": "sphere", "center": list(su.centre), "radius": su.radius,
                   "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0},
                   "interior": {"type": "heterogeneous",
                                "sigma_t": gridvolume(sigma, grid_tf, {"max_value": float(majorant)}),
                                "albedo": gridvolume(albedo, grid_tf), "scale": 1.0,
                                "phase": {"type": "hg", "g": 0.4}, "sample_emitters": False}},
    })


class SpherePeer(Peer):
    """The peer on the sphere scene: its film rows already run from the up side, as ours."""
    key = KEY_SPHERE_SIGMA
    flip_rows = False

    def __init__(self, su, sigma, albedo, max_depth, majorant):
        self.shape = sigma.shape
        self.scene = mitsuba_sphere_scene(su, sigma, albedo, max_depth, majorant)
        self.params = mi.traverse(self.scene)


def _refine(x, f):
    for dim in (1, 2, 3):
        x = x.repeat_interleave(f, dim)
    return x.contiguous()


class SphereOurs:
    def __init__(self, su, sigma, albedo, max_depth, radius=None, refine=1, shift=(0.0, 0.0, 0.0)):
        self.scene = su.ours_scene(max_depth, radius, refine, shift)
        self.sigma, self.albedo = _refine(sigma, refine), _refine(albedo, refine)

    def forward(self, spp, seed):
        with torch.no_grad():
            return ta.render_scene(self.scene, self.sigma, self.albedo, spp=spp, seed=seed)

    def forward_backward(self, spp, seed, weights):
        s = self.sigma.clone().requires_grad_()
        img = ta.render_scene(self.scene, s, self.albedo, spp=spp, seed=seed)
        (img * weights).sum().backward()
        return img.detach(), s.grad


def ztest(a, b, bound=0.0, floor=0.0):
    """Per element |mean a − mean b| (minus ``bound``, clamped at 0) over the standard error of the difference;
    a, b are (seeds, …) stacks. 0 where the difference is 0, inf where it is not but both have no variance."""
    n_a, n_b = a.shape[0], b.shape[0]
    d = a.mean(0) - b.mean(0)
    se = (a.var(0) / n_a + b.var(0) / n_b).sqrt().clamp_min(floor)
    excess = (d.abs() - bound).clamp_min(0)
    z = torch.where(excess == 0, torch.zeros_like(d), excess / se)
    return d, se, z


def sphere_part(args, emit, folder):
    su = SphereSetup(args.sphere_radius, args.voxel_size, args.sphere_res)
    sigma, albedo = su.medium(seed=11)
    n, spp, md = args.sphere_seeds, args.sphere_spp, args.max_depth
    smax = float(sigma.max())
    weights = torch.rand(su.res, su.res, 3, generator=torch.Generator().manual_seed(7))
    ours = SphereOurs(su, sigma, albedo, md)
    peer = SpherePeer(su, sigma, albedo, md, smax)  # tight majorant, as the slab part: primal and timing
    peer_m = SpherePeer(su, sigma, albedo, md, SPHERE_MAJORANT_MARGIN * smax)  # for the gradient

    def runs(r, seed0):
        pairs = [r.forward_backward(spp, seed0 + k, weights) for k in range(n)]
        return (torch.stack([p[i].double() for p in pairs]) for i in (0, 1))

    io_, go_ = runs(ours, 1000)
    # discretisation: our surface is the trilinear zero set, inside the sphere by at most δ; the same walks
    # (common random numbers) on spheres of radius R ± δ give each pixel's and voxel's sensitivity to it
    ip_d, gp_d = runs(SphereOurs(su, sigma, albedo, md, su.radius + su.delta), 1000)
    im_d, gm_d = runs(SphereOurs(su, sigma, albedo, md, su.radius - su.delta), 1000)
    bound_img = torch.maximum((ip_d - io_).mean(0).abs(), (im_d - io_).mean(0).abs())
    bound_grad = torch.maximum((gp_d - go_).mean(0).abs(), (gm_d - go_).mean(0).abs())
    # refinement: voxels split into f³ (the same medium), the SDF sampled at h/f: δ shrinks as 1/f²
    fine = {f: torch.stack([SphereOurs(su, sigma, albedo, md, refine=f).forward(spp, 1000 * f + 1000 + k).double()
                            for k in range(n)]) for f in (2, 4)}
    ipeer, gpeer = runs(peer, 2000)
    ipeer_m, gpeer_m = runs(peer_m, 4000)

    rho, half_diag = su.pixel_rho()
    background = (rho - half_diag > su.radius).unsqueeze(-1).expand(-1, -1, 3)  # footprint misses the sphere
    interior = (rho + half_diag < su.radius - 3 * su.delta).unsqueeze(-1).expand(-1, -1, 3)
    thr = bonferroni(io_[0].numel())
    d_img, se_img, z_raw = ztest(io_, ipeer, floor=SE_FLOOR)
    _, _, z_b = ztest(io_, ipeer, bound_img, floor=SE_FLOOR)
    _, _, z_bm = ztest(io_, ipeer_m, bound_img, floor=SE_FLOOR)
    _, _, z_lr = ztest(io_, ipeer.flip(2), floor=SE_FLOOR)
    _, _, z_ud = ztest(io_, ipeer.flip(1), floor=SE_FLOOR)
    # sensitivity to placement: our medium moved by half a voxel along x (across the view) or z (along it);
    # max z beyond the discretisation bound, as for the unmoved medium
    z_shift = {}
    for axis, shift in (("x", (su.s / 2, 0.0, 0.0)), ("z", (0.0, 0.0, su.s / 2))):
        moved = SphereOurs(su, sigma, albedo, md, shift=shift)
        z_shift[axis] = round(float(ztest(torch.stack([moved.forward(spp, 1000 + k).double() for k in range(n)]),
                                          ipeer, bound_img, floor=SE_FLOOR)[2].max()), 6)

    def sums(a, mask):  # mean over seeds of the sum over a mask, and the variance of that mean
        s_ = a[:, mask].sum(1)
        return s_.mean(), s_.var() / s_.shape[0]

    def rel(num, den):  # relative difference num/den − 1 of independent estimates, standard error by the delta method
        (a, va), (b, vb) = num, den
        return [round(float(a / b - 1), 6), round(float((va / b ** 2 + a ** 2 * vb / b ** 4).sqrt()), 6)]

    sphere_px = ~background
    by_level, by_level_int, z_by_level = {}, {}, {"1": round(float(z_raw.max()), 6)}
    for f, imgs in ((1, io_), (2, fine[2]), (4, fine[4])):
        by_level[str(f)] = rel(sums(imgs, sphere_px), sums(ipeer, sphere_px))
        by_level_int[str(f)] = rel(sums(imgs, interior), sums(ipeer, interior))
        if f > 1:
            z_by_level[str(f)] = round(float(ztest(imgs, ipeer, floor=SE_FLOOR)[2].max()), 6)
    # Richardson (error ∝ h²) from h and h/2: what the difference would be for the exact sphere
    (o1, v1), (o2, v2) = sums(io_, sphere_px), sums(fine[2], sphere_px)
    rel_extrap = rel(((4 * o2 - o1) / 3, (16 * v2 + v1) / 9), sums(ipeer, sphere_px))
    # the same bound on the mean: the larger relative change of our sums at R ± δ (common random numbers)
    mean_bound = {name: max(abs(float(x[:, m].sum(1).mean() / io_[:, m].sum(1).mean() - 1)) for x in (ip_d, im_d))
                  for name, m in (("sphere", sphere_px), ("interior", interior))}

    gthr = bonferroni(go_[0].numel())
    _, _, zg = ztest(go_, gpeer_m)
    _, _, zg_b = ztest(go_, gpeer_m, bound_grad)
    _, _, zg_t = ztest(go_, gpeer)
    sum_o, sum_p = go_.sum((1, 2, 3, 4)), gpeer_m.sum((1, 2, 3, 4))
    worst_t = np.unravel_index(int(zg_t.argmax()), tuple(zg_t.shape))

    # arbiter: central finite differences of the expectation (our smooth explicit-reference estimator, common
    # random numbers) at the voxels where the gradients disagree most, against the channel sums of each gradient
    ref_s, ref_a, h = sigma.double(), albedo.double(), 0.05
    picks = []
    for z in (zg_t, zg):  # the worst voxel against the tight-majorant peer, and against the one we compare
        vox = tuple(int(i) for i in np.unravel_index(int(z.argmax()), tuple(z.shape))[1:])
        if vox not in picks:
            picks.append(vox)
    cases = []
    for vox in picks:
        def fd(k, vox=vox):
            step = torch.zeros_like(ref_s)
            step[(slice(None),) + vox] = h
            f = lambda x: float((ta.render_scene(ours.scene, x, ref_a, spp=2 * spp, seed=700 + k,
                                                 seed_grad=700 + k, sampling_sigma_t=ref_s,
                                                 sampling_albedo=ref_a) * weights.double()).sum())
            return torch.tensor((f(ref_s + step) - f(ref_s - step)) / (2 * h))
        fm, fs = seed_stats(fd, 16)
        case = {"index_dhw": list(vox), "null_density_tight": smax - float(sigma[0][vox]), "fd": float(fm),
                "fd_se": float(fs)}
        for name, g in (("ours", go_), ("peer_tight", gpeer), ("peer_margin", gpeer_m)):
            v = g[(slice(None), slice(None)) + vox].sum(1)
            case[name] = float(v.mean())
            case[name + "_z"] = float((v.mean() - fm).abs() / (v.var() / n + fs ** 2).sqrt())
        cases.append(case)

    # timing at equal spp after warm-up (the peer JIT-compiles), medians
    fns = {"ours_forward_s": lambda r: ours.forward(spp, r), "peer_forward_s": lambda r: peer.forward(spp, r),
           "ours_forward_backward_s": lambda r: ours.forward_backward(spp, r, weights),
           "peer_forward_backward_s": lambda r: peer.forward_backward(spp, r, weights),
           "peer_margin_forward_backward_s": lambda r: peer_m.forward_backward(spp, r, weights)}
    for fn in fns.values():
        fn(99)
    times = {k: timed(fn, args.reps) for k, fn in fns.items()}

    fail = (z_b > thr)
    emit({"part": "sphere", "pixels": su.res ** 2, "grid_dhw": list(su.shape), "voxel_mm": su.s,
          "radius_mm": su.radius, "seeds": n, "spp": spp, "delta_mm": su.delta,
          "primal_threshold": thr, "primal_max_z": float(z_raw.max()), "primal_outside_noise": int((z_raw > thr).sum()),
          "primal_max_z_beyond_bound": float(z_b.max()), "primal_outside_bound_noise": int(fail.sum()),
          "primal_outside_bound_noise_peer_margin": int((z_bm > thr).sum()),
          "primal_max_z_interior": float(z_raw[interior].max()), "interior_pixels": int(interior[..., 0].sum()),
          "primal_max_z_peer_flipped_lr": float(z_lr.max()), "primal_max_z_peer_flipped_ud": float(z_ud.max()),
          "primal_max_z_beyond_bound_ours_medium_moved_half_voxel": z_shift,
          "bound_max": float(bound_img.max()), "bound_mean_sphere": float(bound_img[sphere_px].mean()),
          "se_median_sphere": float(se_img[sphere_px].median()),
          "mean_rel_diff": by_level["1"][0], "mean_rel_diff_se": by_level["1"][1],
          "mean_rel_bound": mean_bound["sphere"],
          "mean_rel_diff_interior": by_level_int["1"][0], "mean_rel_diff_interior_se": by_level_int["1"][1],
          "mean_rel_bound_interior": mean_bound["interior"],
          "refine_factors": [1, 2, 4], "mean_rel_diff_by_refine": by_level,
          "mean_rel_diff_interior_by_refine": by_level_int, "primal_max_z_by_refine": z_by_level,
          "mean_rel_diff_extrapolated_h0": rel_extrap,
          "primal_mean_ours": float(io_.mean()), "primal_mean_peer": float(ipeer.mean()),
          "background_pixels": int(background[..., 0].sum()),
          "background_max_dev_ours": float((io_[:, background] - 1).abs().max()),
          "background_max_dev_peer": float((ipeer[:, background] - 1).abs().max()),
          "grad_majorant_margin": SPHERE_MAJORANT_MARGIN, "grad_threshold": gthr, "grad_max_z": float(zg.max()),
          "grad_max_z_beyond_bound": float(zg_b.max()), "grad_outside_bound_noise": int((zg_b > gthr).sum()),
          "grad_frac_z_gt_3": float((zg > 3).double().mean()),
          "grad_sum_ours": float(sum_o.mean()), "grad_sum_peer": float(sum_p.mean()),
          "grad_sum_rel_diff": float(sum_o.mean() / sum_p.mean() - 1),
          "grad_sum_se": [round(float(x.std() / n ** .5), 6) for x in (sum_o, sum_p)],
          "grad_max_z_peer_tight": float(zg_t.max()), "grad_outside_peer_tight": int((zg_t > gthr).sum()),
          "grad_worst_peer_tight_cdhw": [int(i) for i in worst_t],
          "arbiter": [{k: (round(v, 6) if isinstance(v, float) else v) for k, v in c.items()} for c in cases],
          "threads": torch.get_num_threads(), **times,
          "ratio_forward": times["peer_forward_s"] / times["ours_forward_s"],
          "ratio_forward_backward": times["peer_forward_backward_s"] / times["ours_forward_backward_s"]})
    _plot_sphere(io_.mean(0), ipeer.mean(0), d_img, fail, su, float(z_raw.max()), float(z_b.max()), thr,
                 os.path.join(folder, "sphere.png"))


def _plot_sphere(ours_img, peer_img, diff, fail, su, zmax_raw, zmax_bound, thr, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle
    from torch_appearance.color import linear_to_srgb

    fig, ax = plt.subplots(1, 3, figsize=(12, 4.2))
    c = (su.res - 1) / 2
    r_px = su.radius / (su.extent / su.res)
    for a, img, title in ((ax[0], ours_img, "torch_appearance (SDF sphere)"),
                          (ax[1], peer_img, "Mitsuba 3 prbvolpath")):
        a.imshow(linear_to_srgb(img.clamp(0, 1)).numpy(), interpolation="nearest")
        a.set_title(title, fontsize=10)
    d = diff.mean(-1).numpy()
    lim = float(np.abs(d).max()) or 1.0
    im = ax[2].imshow(d, cmap="coolwarm", vmin=-lim, vmax=lim, interpolation="nearest")
    fig.colorbar(im, ax=ax[2], fraction=0.046, label="difference (mean of R, G, B)")
    rows, cols = np.nonzero(fail.any(-1).numpy())
    ax[2].plot(cols, rows, "kx", ms=6, label="beyond bound + noise")
    ax[2].set_title(f"ours − Mitsuba\nmax |z| {zmax_raw:.2f}, beyond the bound {zmax_bound:.2f} "
                    f"(threshold {thr:.2f})", fontsize=9)
    for a in ax:
        a.add_patch(Circle((c, c), r_px, fill=False, ec="k", lw=0.6, ls="--"))
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle(f"grid medium in a dielectric sphere (IOR 1.5), R = {su.radius} mm, voxel {su.s} mm, "
                 f"{su.res}×{su.res} orthographic pixels; dashed: the exact silhouette", fontsize=10)
    fig.tight_layout()
    ta_io.save_figure(fig, path)


# ------------------------------------------------------------------------------------------------ main
def main(argv=None):
    global mi, dr
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, default=32, help="texels per side of the agreement scenes (default: %(default)s)")
    p.add_argument("--depth", type=int, default=12, help="voxel layers (default: %(default)s)")
    p.add_argument("--voxel-size", type=float, default=0.085, help="mm (default: %(default)s)")
    p.add_argument("--seeds", type=int, default=16, help="independent renders per agreement estimate (default: %(default)s)")
    p.add_argument("--spp", type=int, default=64, help="spp of each agreement render (default: %(default)s)")
    p.add_argument("--timing-size", type=int, default=64, help="texels per side of the timing scene (default: %(default)s)")
    p.add_argument("--timing-spp", type=int, default=16, help="(default: %(default)s)")
    p.add_argument("--reps", type=int, default=5, help="timed repetitions (default: %(default)s)")
    p.add_argument("--max-depth", type=int, default=1024, help="interaction limit in both (default: %(default)s)")
    p.add_argument("--sphere-radius", type=float, default=0.6, help="mm, sphere part (default: %(default)s)")
    p.add_argument("--sphere-res", type=int, default=24, help="pixels per side of the sphere image (default: %(default)s)")
    p.add_argument("--sphere-spp", type=int, default=256,
                   help="spp of each sphere render and of its timing (default: %(default)s)")
    p.add_argument("--sphere-seeds", type=int, default=32,
                   help="independent renders per sphere estimate (default: %(default)s)")
    p.add_argument("--skip", default="",
                   help="comma-separated parts to skip: agreement,chromatic,timing,efficiency,sphere")
    p.add_argument("--out", default="results/bench/peer.jsonl", help="JSON lines; plots beside it (default: %(default)s)")
    args = p.parse_args(argv)
    mi, dr = _load_mitsuba()
    skip = set(filter(None, args.skip.split(",")))
    lines = []
    folder = os.path.dirname(args.out) or "."
    os.makedirs(folder, exist_ok=True)

    def emit(d):
        d = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in d.items()}
        print(json.dumps(d), flush=True)
        lines.append(d)

    s = args.voxel_size
    # ---- grey scene: primal and gradient agreement
    sigma, albedo = make_scene("grey", args.size, args.depth)
    ours, peer = Ours(sigma, albedo, s, args.max_depth), Peer(sigma, albedo, s, args.max_depth)
    weights = torch.rand(args.size, args.size, 3, generator=torch.Generator().manual_seed(5))
    if "agreement" not in skip:
        pair_o = [ours.forward_backward(args.spp, 1000 + k, weights) for k in range(args.seeds)]
        pair_p = [peer.forward_backward(args.spp, 2000 + k, weights) for k in range(args.seeds)]
        io_, go_ = (torch.stack([x[i].double() for x in pair_o]) for i in (0, 1))
        ip_, gp_ = (torch.stack([x[i].double() for x in pair_p]) for i in (0, 1))
        n = args.seeds
        zi, _ = zmax(io_.mean(0), io_.std(0) / n ** .5, ip_.mean(0), ip_.std(0) / n ** .5)
        zg, zgall = zmax(go_.mean(0), go_.std(0) / n ** .5, gp_.mean(0), gp_.std(0) / n ** .5)
        rel = float((go_.mean(0).sum() - gp_.mean(0).sum()) / gp_.mean(0).sum().abs())
        # arbiter: central finite difference of the expectation along "all σ_t + h" (our smooth explicit-reference
        # estimator, common random numbers), against the sum of each renderer's gradient
        h, ref_s, ref_a = 0.05, sigma.double(), albedo.double()

        def fd(k):
            f = lambda x: float((ta.render_texels(x, ref_a, voxel_size=s, spp=args.spp * 4, seed=700 + k,
                                                  max_depth=args.max_depth, sampling_sigma_t=ref_s,
                                                  sampling_albedo=ref_a) * weights.double()).sum())
            return torch.tensor((f(ref_s + h) - f(ref_s - h)) / (2 * h))

        fd_mean, fd_se = seed_stats(fd, n)
        sum_o, sum_p = go_.sum((1, 2, 3, 4)), gp_.sum((1, 2, 3, 4))
        z_fd = lambda x: float((x.mean() - fd_mean).abs() / ((x.std() / n ** .5) ** 2 + fd_se ** 2).sqrt())
        emit({"part": "agreement_grey", "fd_directional": float(fd_mean), "fd_se": float(fd_se),
              "ours_grad_sum_se": float(sum_o.std() / n ** .5), "peer_grad_sum_se": float(sum_p.std() / n ** .5),
              "ours_z_vs_fd": z_fd(sum_o), "peer_z_vs_fd": z_fd(sum_p), "texels": args.size ** 2, "depth": args.depth, "seeds": n, "spp": args.spp,
              "primal_max_z": zi, "primal_threshold": bonferroni(io_[0].numel()),
              "primal_mean_ours": float(io_.mean()), "primal_mean_peer": float(ip_.mean()),
              "grad_max_z": zg, "grad_threshold": bonferroni(go_[0].numel()),
              "grad_frac_z_gt_3": float((zgall > 3).double().mean()),
              "grad_sum_ours": float(go_.mean(0).sum()), "grad_sum_peer": float(gp_.mean(0).sum()),
              "grad_sum_rel_diff": rel})

        # arbiter per voxel: where the renderers disagree most, central finite differences of the expectation
        top = torch.topk(zgall.flatten(), 8).indices
        fd_vox = []
        for flat in top.tolist():
            def fd_one(k, flat=flat):
                step = torch.zeros_like(ref_s).view(-1)
                step[flat] = h
                step = step.view_as(ref_s)
                f = lambda x: float((ta.render_texels(x, ref_a, voxel_size=s, spp=args.spp * 4, seed=1700 + k,
                                                      max_depth=args.max_depth, sampling_sigma_t=ref_s,
                                                      sampling_albedo=ref_a) * weights.double()).sum())
                return torch.tensor((f(ref_s + step) - f(ref_s - step)) / (2 * h))
            fm, fs = seed_stats(fd_one, n)
            o, po = go_.reshape(n, -1)[:, flat], gp_.reshape(n, -1)[:, flat]
            zo = float((o.mean() - fm).abs() / ((o.std() / n ** .5) ** 2 + fs ** 2).sqrt())
            zp = float((po.mean() - fm).abs() / ((po.std() / n ** .5) ** 2 + fs ** 2).sqrt())
            fd_vox.append({"index_cdhw": list(np.unravel_index(flat, tuple(go_.shape[1:]))), "fd": float(fm),
                           "fd_se": float(fs), "ours": float(o.mean()), "peer": float(po.mean()),
                           "ours_z": zo, "peer_z": zp})
        emit({"part": "gradient_arbiter", "voxels": len(fd_vox),
              "ours_max_z_vs_fd": max(v["ours_z"] for v in fd_vox),
              "peer_max_z_vs_fd": max(v["peer_z"] for v in fd_vox),
              "cases": [{k: ([int(i) for i in x] if k == "index_cdhw" else round(x, 5)) for k, x in v.items()} for v in fd_vox]})

    # ---- chromatic: both against the independent numpy reference
    if "chromatic" not in skip:
        from torch_appearance.testing.reference_tracer import reference_render_texels
        cs, ca = make_scene("chromatic", 6, 4, seed=3)
        ref_mean, ref_se = reference_render_texels(cs.double().numpy(), ca.double().numpy(), voxel_size=0.1,
                                                   g=0.4, ior=1.5, spp=20000, seed=1, max_depth=args.max_depth)
        ref_mean, ref_se = torch.from_numpy(ref_mean), torch.from_numpy(ref_se)
        o = Ours(cs, ca, 0.1, args.max_depth)
        pr = Peer(cs, ca, 0.1, args.max_depth)
        om, ose = seed_stats(lambda k: o.forward(256, 3000 + k), 32)
        pm, pse = seed_stats(lambda k: pr.forward(256, 4000 + k), 32)
        zo, _ = zmax(om, ose, ref_mean, ref_se)
        zp, _ = zmax(pm, pse, ref_mean, ref_se)
        rel_o = ((om - ref_mean) / ref_mean).mean((0, 1))
        rel_p = ((pm - ref_mean) / ref_mean).mean((0, 1))
        emit({"part": "chromatic_bias", "texels": 36, "threshold": bonferroni(om.numel()),
              "ours_max_z": zo, "peer_max_z": zp,
              "ours_mean_rel_bias_rgb": [float(v) for v in rel_o], "peer_mean_rel_bias_rgb": [float(v) for v in rel_p],
              "reference_mean_rgb": [float(v) for v in ref_mean.mean((0, 1))]})

    # ---- timing at equal spp
    if "timing" not in skip:
        ts, ta_ = make_scene("grey", args.timing_size, args.depth, seed=1)
        o, pr = Ours(ts, ta_, s, args.max_depth), Peer(ts, ta_, s, args.max_depth)
        w = torch.rand(args.timing_size, args.timing_size, 3, generator=torch.Generator().manual_seed(6))
        for fn in (lambda r: o.forward(args.timing_spp, r), lambda r: pr.forward(args.timing_spp, r),
                   lambda r: o.forward_backward(args.timing_spp, r, w), lambda r: pr.forward_backward(args.timing_spp, r, w)):
            fn(99)  # warm-up (the peer JIT-compiles its kernels)
        fo = timed(lambda r: o.forward(args.timing_spp, r), args.reps)
        fp = timed(lambda r: pr.forward(args.timing_spp, r), args.reps)
        bo = timed(lambda r: o.forward_backward(args.timing_spp, r, w), args.reps)
        bp = timed(lambda r: pr.forward_backward(args.timing_spp, r, w), args.reps)
        emit({"part": "timing", "texels": args.timing_size ** 2, "depth": args.depth, "spp": args.timing_spp,
              "threads": torch.get_num_threads(), "ours_forward_s": fo, "peer_forward_s": fp,
              "ours_forward_backward_s": bo, "peer_forward_backward_s": bp,
              "ratio_forward": fp / fo, "ratio_forward_backward": bp / bo})

    # ---- error against time
    if "efficiency" not in skip:
        ref_img, _ = seed_stats(lambda k: ours.forward(256, 5000 + k), 16)
        ref_grad = torch.stack([ours.forward_backward(256, 6000 + k, weights)[1].double() for k in range(16)]).mean(0)
        rows = []
        for spp in (1, 2, 4, 8, 16, 32):
            for name, r in (("ours", ours), ("peer", peer)):
                r.forward_backward(spp, 77, weights)  # warm-up for this spp
                errs_i, errs_g, tf, tb = [], [], [], []
                for k in range(4):
                    t = time.perf_counter()
                    img = r.forward(spp, 8000 + k)
                    tf.append(time.perf_counter() - t)
                    t = time.perf_counter()
                    _, g = r.forward_backward(spp, 9000 + k, weights)
                    tb.append(time.perf_counter() - t)
                    errs_i.append(float(((img.double() - ref_img) ** 2).mean().sqrt()))
                    errs_g.append(float(((g.double() - ref_grad) ** 2).mean().sqrt()))
                row = {"renderer": name, "spp": spp, "forward_s": statistics.median(tf),
                       "forward_backward_s": statistics.median(tb), "rmse_image": statistics.mean(errs_i),
                       "rmse_grad": statistics.mean(errs_g)}
                rows.append(row)
                emit({"part": "efficiency", **row})
        ta_io.write_json(os.path.join(folder, "efficiency.json"), rows)
        _plot(rows, os.path.join(folder, "efficiency.png"))

    # ---- sphere: the peer's analytic dielectric sphere against our SDF boundary
    if "sphere" not in skip:
        sphere_part(args, emit, folder)
    ta_io.atomic_write_bytes(args.out, ("\n".join(json.dumps(d) for d in lines) + "\n").encode())
    return 0


def _plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for name, style in (("ours", "o-"), ("peer", "s--")):
        r = [x for x in rows if x["renderer"] == name]
        label = "torch_appearance" if name == "ours" else "Mitsuba 3 prbvolpath"
        ax[0].loglog([x["forward_s"] for x in r], [x["rmse_image"] for x in r], style, label=label)
        ax[1].loglog([x["forward_backward_s"] for x in r], [x["rmse_grad"] for x in r], style, label=label)
    ax[0].set(xlabel="forward wall time [s]", ylabel="RMSE of the image", title="primal: error vs time")
    ax[1].set(xlabel="forward + backward wall time [s]", ylabel="RMSE of ∂(Σ w·image)/∂σ_t",
              title="gradient: error vs time")
    for a in ax:
        a.legend(fontsize=8)
        a.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    ta_io.save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
