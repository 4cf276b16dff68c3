"""Bundle adjustment through a flat water surface: camera poses and track points re-solved so that every
observation of a submerged point is its projection through the water (`refraction.apparent_points_each`, the
RA-GS transform), every other one a plain pinhole projection, with the cameras held near their measured
positions (RTK) when given.

Why: a pinhole bundle adjustment makes the straight rays of the submerged tracks meet at the apparent bed,
and it gets there partly by tilting the cameras (1.3 degrees median on the `small` reach, more for
oblique views); rays bent at the water from those cameras then overshoot the bed by tens of centimetres.
Projecting the submerged tracks through the water removes the reason for the tilt (R-SfM, 2024, does this
inside OpenSfM).

The solver is Levenberg-Marquardt on all poses and points at once, in float64: the Jacobian blocks of every
observation (it depends on one camera and one point) by autograd, the points eliminated by the Schur
complement, Huber weights against wrong matches. Intrinsics are held fixed. The reduced system in the cameras
has a 6 x 6 block for each pair of cameras that see a common point; its blocks are gathered a bounded number
of observation pairs at a time (`PAIR_CHUNK`), so memory grows with the observations and the camera pairs,
not with the observation pairs (one per two observations of a point: a million on the `small` reach). Up to
`DENSE_MAX` unknowns it is solved dense on the tensors' device; a larger survey's system, sparse as its
flight's overlap, by SciPy's sparse LU on the CPU. Tensors in, tensors out, float64, CPU or CUDA.

The water surface itself may be adjusted with them (`free`: its level, or its level and slope), as
multimedia photogrammetry estimates an interface in the bundle (Mulsow, 2010): a level error moves a
submerged point's apparent position differently at different incidence angles, so tracks seen from nadir and
oblique views fix it. Only near nadir is it lost (there the apparent depth is d / n at every angle, and a
level and the points' depths trade against each other).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch

from ragsplat.refraction import apparent_points_each
from ragsplat.water_surface import WaterSurface, float_value


def skew(w: torch.Tensor) -> torch.Tensor:  # [N, 3] -> [N, 3, 3]
    z = torch.zeros_like(w[:, 0])
    return torch.stack([torch.stack([z, -w[:, 2], w[:, 1]], -1), torch.stack([w[:, 2], z, -w[:, 0]], -1),
                        torch.stack([-w[:, 1], w[:, 0], z], -1)], -2)


def project(R: torch.Tensor, C: torch.Tensor, intrinsics: torch.Tensor, X: torch.Tensor,
            water: WaterSurface | None, lens: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    """[M, 2] pixel positions (centres at i + 0.5) of points X [M, 3] seen by cameras R [M, 3, 3] (world ->
    camera), centres C [M, 3], intrinsics [M, 4] (fx, fy, cx, cy), one camera per point, through a lens
    with radial distortion `lens` = (k1, k2) (COLMAP's RADIAL: x (1 + k1 r^2 + k2 r^4) in normalised
    coordinates); a point below the water surface is seen at its apparent position through the water."""
    if water is not None:
        X = apparent_points_each(X, C, water)
    xc = (R @ (X - C)[:, :, None])[:, :, 0]  # [M, 3]
    xy = xc[:, :2] / xc[:, 2:]
    if any(lens):
        r2 = (xy * xy).sum(-1, keepdim=True)
        xy = xy * (1 + lens[0] * r2 + lens[1] * r2 * r2)
    k = intrinsics
    return torch.stack([k[:, 0] * xy[:, 0] + k[:, 2], k[:, 1] * xy[:, 1] + k[:, 3]], -1)


@dataclass(frozen=True)
class Bundle:
    """The adjusted cameras and points, and how well they explain the observations."""

    R: torch.Tensor  # [I, 3, 3] world -> camera
    C: torch.Tensor  # [I, 3] camera centres
    points: torch.Tensor  # [P, 3]
    residuals: torch.Tensor  # [M] reprojection error (pixels) of every observation
    iterations: int
    cost: float  # robust cost at the end (pixels^2 units, priors included)
    water: WaterSurface | None = None  # the surface, adjusted where `free` asked
    sigma: dict[str, float] | None = None  # standard deviation of each free parameter (m; slope: m/m)
    # the same with the cameras held where they are (where the positions fix the frame only to metres,
    # `sigma` is mostly the frame's own uncertainty; this one leaves out how the cameras trade with the level)
    sigma_given_cameras: dict[str, float] | None = None
    lens: tuple[float, float] = (0.0, 0.0)  # (k1, k2): adjusted where `free` asked
    # the level's standard deviation relative to the submerged points' mean height (m; `_level_to_bed`): the
    # depths' common offset, what they depend on, the cameras and the points free to trade with it
    sigma_level_to_bed: float | None = None


def _rotate(R: torch.Tensor, w: torch.Tensor) -> torch.Tensor:  # R [N, 3, 3] turned by w [N, 3] (radians)
    return R @ torch.linalg.matrix_exp(skew(w))


def _huber(s: torch.Tensor, delta: float) -> tuple[torch.Tensor, torch.Tensor]:  # (cost, IRLS weight) of |r|
    cost = torch.where(s <= delta, s * s, 2 * delta * s - delta * delta)
    return cost, torch.where(s <= delta, torch.ones_like(s), delta / s.clamp(min=1e-300))


def adjust(R: torch.Tensor, C: torch.Tensor, intrinsics: torch.Tensor, points: torch.Tensor,
           point: torch.Tensor, image: torch.Tensor, pixels: torch.Tensor, water: WaterSurface | None,
           prior_C: torch.Tensor | None = None,
           prior_sigma: tuple[float, float, float] | torch.Tensor = (0.02, 0.02, 0.03),
           prior_points: tuple[torch.Tensor, torch.Tensor] | None = None, point_sigma: float = 0.01,
           pixel_sigma: float = 1.0, huber: float = 2.0, iterations: int = 30, tol: float = 1e-9,
           free: tuple[str, ...] = (), lens: tuple[float, float] = (0.0, 0.0), on_iteration=None,
           sparse: bool | None = None) -> Bundle:
    """Levenberg-Marquardt on the cameras (R [I, 3, 3], C [I, 3]) and points [P, 3] given the observations
    pixels [M, 2] of point [M] in image [M], the intrinsics [I, 4] held fixed. Cost: sum of Huber(|r| /
    pixel_sigma) over the observations plus, with `prior_C` [I, 3], sum of ((C - prior_C) / prior_sigma)^2
    (metres; x, y, z, the same for every camera or one row [I, 3] each; rows of NaN: no prior), which also
    fixes the frame; with `prior_points` (indices [G], positions [G, 3]: ground control points among the
    points) sum of ((P - position) / point_sigma)^2, which fixes it too; without either the frame floats
    (damped only). `lens`: every camera's radial distortion (k1, k2; `project`). `free` ("level", "slope",
    "lens"): the water's parameters (a flat or tilted plane) or the lens's adjusted too, shared by all
    observations (their Jacobian columns by central differences), their standard deviations from the final
    normal equations scaled by the residuals' variance (and with the cameras held). Stops after
    `iterations` or when an accepted step lowers the cost by less than `tol` relative; `on_iteration(cost)`
    after each. `sparse`: the reduced system solved sparse on the CPU (True) or dense on the tensors' device
    (False); None: sparse above `DENSE_MAX` unknowns."""
    dt = torch.float64
    R, C, points, intrinsics, pixels = (x.to(dt) for x in (R, C, points, intrinsics, pixels))
    index = _free_index(free, water)  # which of (level, slope x, slope y, k1, k2) are adjusted
    sparse = 6 * len(C) + len(index) > DENSE_MAX if sparse is None else sparse
    problem = _Problem(C, intrinsics, len(points), point, image, pixels, water, index, prior_C, prior_sigma,
                       prior_points, point_sigma, pixel_sigma, huber, sparse)
    start = [0.0, 0.0, 0.0] if water is None else [float_value(water.level), *map(float_value, water.slope)]
    theta = torch.tensor(start, dtype=dt)
    theta = torch.cat([theta, torch.tensor([float(v) for v in lens], dtype=dt)])
    fit = _levenberg_marquardt(problem, _State(R, C, points, theta), iterations, tol, on_iteration)
    sigma, held, to_bed = _sigmas(problem, fit) if len(index) else (None, None, None)
    end = fit.state
    return Bundle(end.R, end.C, end.points, (fit.r * pixel_sigma).norm(dim=-1), fit.iterations, fit.cost,
                  problem.surface(end.theta), sigma, held, problem.distortion(end.theta), to_bed)


@dataclass(frozen=True)
class _State:
    """The unknowns: the cameras, the points and the shared parameters (`PARAMETERS`, all five)."""

    R: torch.Tensor  # [I, 3, 3]
    C: torch.Tensor  # [I, 3]
    points: torch.Tensor  # [P, 3]
    theta: torch.Tensor  # [5]


@dataclass(frozen=True)
class _Fit:
    """Where Levenberg-Marquardt stopped: the state, its cost and residuals, the iterations it took."""

    state: _State
    cost: float
    r: torch.Tensor  # [M, 2] in units of pixel_sigma
    iterations: int


class _Problem:
    """What stays fixed while `adjust` iterates (the observations, the priors, the free parameters, how the
    reduced system is solved), and what it makes of a `_State`: the residuals, the robust cost, the Jacobians,
    the normal equations, the reduced system and the damped step."""

    def __init__(self, C: torch.Tensor, intrinsics: torch.Tensor, n_pts: int, point: torch.Tensor,
                 image: torch.Tensor, pixels: torch.Tensor, water: WaterSurface | None, index: list[int],
                 prior_C: torch.Tensor | None, prior_sigma, prior_points, point_sigma: float,
                 pixel_sigma: float, huber: float, sparse: bool):
        dt = self.dt = torch.float64
        self.device = C.device
        self.n_img, self.n_pts = len(C), n_pts
        self.point, self.image, self.pixels, self.water, self.index = point, image, pixels, water, index
        self.point_sigma, self.pixel_sigma, self.huber, self.sparse = point_sigma, pixel_sigma, huber, sparse
        self.sig = None if prior_C is None else torch.as_tensor(prior_sigma, dtype=dt, device=C.device)
        self.held = None  # [I, 1] bool: the cameras with a prior
        if prior_C is not None:  # a camera without a position (NaN) has no prior
            prior_C = prior_C.to(dt)
            self.held = torch.isfinite(prior_C).all(1)[:, None]
            prior_C = torch.where(self.held, prior_C, C)
        self.prior_C = prior_C
        self.couples = _Couples(point, image, n_pts, self.n_img)  # where the Schur complement couples cameras
        self.K = intrinsics[image]
        self.eye3 = torch.eye(3, dtype=dt, device=C.device)
        self.fd_step = torch.tensor(FD_STEP, dtype=dt)
        self.gcp, self.gcp_xyz = (None, None) if prior_points is None else (prior_points[0],
                                                                             prior_points[1].to(dt))

    def surface(self, th: torch.Tensor) -> WaterSurface | None:
        if not any(j < 3 for j in self.index):
            return self.water
        return WaterSurface(float(th[0]), self.water.n, (float(th[1]), float(th[2])))

    def distortion(self, th: torch.Tensor) -> tuple[float, float]:
        return float(th[3]), float(th[4])

    def residual(self, R_, C_, P_, th):  # [M, 2] in units of pixel_sigma
        return (project(R_[self.image], C_[self.image], self.K, P_[self.point], self.surface(th),
                        self.distortion(th)) - self.pixels) / self.pixel_sigma

    def total(self, s: _State) -> tuple[float, torch.Tensor]:
        """(the robust cost with the priors, the residuals [M, 2]) at `s`."""
        r = self.residual(s.R, s.C, s.points, s.theta)
        cost = _huber(r.norm(dim=-1), self.huber)[0].sum()
        if self.sig is not None:
            cost = cost + ((self.held * (s.C - self.prior_C) / self.sig) ** 2).sum()
        if self.gcp is not None:
            cost = cost + (((s.points[self.gcp] - self.gcp_xyz) / self.point_sigma) ** 2).sum()
        return float(cost), r

    def jacobians(self, s: _State) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """[M, 2, 6], [M, 2, 3] and [M, 2, G]: each observation's residual w.r.t. its camera (turn, centre),
        its point and the free water parameters. The first two by autograd (exact; the water's through its
        implicit gradients): one backward per pixel axis, the parameters repeated per observation so that the
        gradient of the sum is each one's own row; the water's, shared by all, by central differences."""
        dt, point, image, th, fd_step = self.dt, self.point, self.image, s.theta, self.fd_step
        with torch.enable_grad():
            turn = torch.zeros(len(point), 3, dtype=dt, device=self.device, requires_grad=True)
            Cm = s.C[image].detach().requires_grad_(True)
            X = s.points[point].detach().requires_grad_(True)
            r_ = (project(s.R[image] @ (self.eye3 + skew(turn)), Cm, self.K, X, self.surface(th),
                          self.distortion(th)) - self.pixels) / self.pixel_sigma
            rows = [torch.autograd.grad(r_[:, a].sum(), (turn, Cm, X), retain_graph=a == 0) for a in range(2)]
        Jg = [(self.residual(s.R, s.C, s.points, th + e) - self.residual(s.R, s.C, s.points, th - e))
              / (2 * fd_step[j]) for j in self.index for e in [fd_step[j] * (torch.arange(len(th)) == j)]]
        Jg = torch.stack(Jg, -1) if Jg else torch.zeros(len(point), 2, 0, dtype=dt, device=self.device)
        return torch.stack([torch.cat(g[:2], -1) for g in rows], 1), torch.stack([g[2] for g in rows], 1), Jg

    def normal_equations(self, s: _State, r: torch.Tensor) -> dict:
        """The Gauss-Newton blocks at `s`, with the Huber weights of its residuals r."""
        dt, dev, point, image = self.dt, self.device, self.point, self.image
        n_img, n_pts = self.n_img, self.n_pts
        Jc, Jp, Jg = self.jacobians(s)
        w = _huber(r.norm(dim=-1), self.huber)[1][:, None, None]  # [M, 1, 1]
        wr = w * r[:, :, None]
        U = torch.zeros(n_img, 6, 6, dtype=dt, device=dev).index_add_(0, image, Jc.mT @ (w * Jc))
        V = torch.zeros(n_pts, 3, 3, dtype=dt, device=dev).index_add_(0, point, Jp.mT @ (w * Jp))
        gc = torch.zeros(n_img, 6, dtype=dt, device=dev).index_add_(0, image, (Jc.mT @ wr)[..., 0])
        gp = torch.zeros(n_pts, 3, dtype=dt, device=dev).index_add_(0, point, (Jp.mT @ wr)[..., 0])
        if self.sig is not None:
            U[:, 3:, 3:] += self.held[:, :, None] * torch.diag_embed((1 / self.sig**2).expand(n_img, 3))
            gc[:, 3:] += self.held * (s.C - self.prior_C) / self.sig**2
        if self.gcp is not None:
            V[self.gcp] += self.eye3 / self.point_sigma**2
            gp[self.gcp] += (s.points[self.gcp] - self.gcp_xyz) / self.point_sigma**2
        G = Jg.shape[-1]
        Ucg = torch.zeros(n_img, 6, G, dtype=dt, device=dev).index_add_(0, image, Jc.mT @ (w * Jg))
        Wg = torch.zeros(n_pts, G, 3, dtype=dt, device=dev).index_add_(0, point, Jg.mT @ (w * Jp))
        return {"U": U, "V": V, "W": Jc.mT @ (w * Jp), "gc": gc, "gp": gp, "Ugg": (Jg.mT @ (w * Jg)).sum(0),
                "Ucg": Ucg, "Wg": Wg, "gg": (Jg.mT @ wr)[..., 0].sum(0)}

    def reduced(self, eq: dict, lam: float):
        """The damped system in the cameras and the water's parameters, the points eliminated (Schur
        complement): (`_System`, right-hand side [6I + G], the points' inverse blocks [P, 3, 3])."""
        point, image, n_img = self.point, self.image, self.n_img
        U, V, W, Ugg = eq["U"], eq["V"], eq["W"], eq["Ugg"]
        Ud = U + lam * torch.diag_embed(torch.diagonal(U, dim1=-2, dim2=-1) + 1e-9)
        Vd = V + lam * torch.diag_embed(torch.diagonal(V, dim1=-2, dim2=-1)) + 1e-12 * self.eye3
        Vi = torch.linalg.inv(Vd)  # [P, 3, 3]
        Y = W @ Vi[point]  # [M, 6, 3]
        blocks = self.couples.gather(Y, W)  # [B, 6, 6]: -sum of Y_a W_b^T over the pairs of each camera pair
        blocks[self.couples.diagonal] += Ud
        rhs = -eq["gc"] + torch.zeros(n_img, 6, dtype=self.dt, device=self.device).index_add_(
            0, image, (Y @ eq["gp"][point][:, :, None])[..., 0])
        rhs = rhs.reshape(-1)
        Scg = Sgg = None
        if len(self.index):  # the water's parameters: one more row and column each
            Wg, Z = eq["Wg"], eq["Wg"] @ Vi  # [P, G, 3]
            Scg = eq["Ucg"] - torch.zeros_like(eq["Ucg"]).index_add_(0, image, Y @ Wg[point].mT)
            Sgg = Ugg + lam * torch.diag_embed(torch.diagonal(Ugg) + 1e-9) - (Z @ Wg.mT).sum(0)
            Scg = Scg.reshape(6 * n_img, -1)
            rhs = torch.cat([rhs, -eq["gg"] + (Z @ eq["gp"][:, :, None])[..., 0].sum(0)])
        return _System(self.couples, blocks, Scg, Sgg, self.sparse), rhs, Vi

    def step(self, s: _State, eq: dict, lam: float) -> _State:
        """The state after the damped Gauss-Newton step from `s` (normal equations `eq`, damping `lam`): the
        cameras and the shared parameters solved, the points back-substituted."""
        n_img = self.n_img
        S, rhs, Vi = self.reduced(eq, lam)
        x = S.solve(rhs)
        dc, dg = x[: 6 * n_img].reshape(n_img, 6), x[6 * n_img:]
        back = torch.zeros(self.n_pts, 3, dtype=self.dt, device=self.device).index_add_(
            0, self.point, (eq["W"].mT @ dc[self.image][:, :, None])[..., 0])
        if len(self.index):
            back = back + (eq["Wg"].mT @ dg)
        dp = -(Vi @ (eq["gp"] + back)[:, :, None])[..., 0]
        th1 = s.theta.clone()
        th1[self.index] += dg
        return _State(_rotate(s.R, dc[:, :3]), s.C + dc[:, 3:], s.points + dp, th1)


def _levenberg_marquardt(problem: _Problem, state: _State, iterations: int, tol: float, on_iteration) -> _Fit:
    """Steps from `state` while they lower the cost (the damping down by 3 after an accepted step, up by 4
    after a rejected one), until `iterations`, a relative decrease under `tol`, or a damping over 1e12."""
    cost, r = problem.total(state)
    lam, it = 1e-3, 0
    for it in range(1, iterations + 1):
        eq = problem.normal_equations(state, r)
        while True:
            trial = problem.step(state, eq, lam)
            new, r1 = problem.total(trial)
            if new < cost:
                done = cost - new < tol * cost
                state, cost, r = trial, new, r1
                lam = max(lam / 3, 1e-12)
                break
            lam *= 4
            if lam > 1e12:
                done = True
                break
        if on_iteration is not None:
            on_iteration(cost)
        if done:
            break
    return _Fit(state, cost, r, it)


def _sigmas(problem: _Problem, fit: _Fit) -> tuple[dict[str, float], dict[str, float], float | None]:
    """The free parameters' standard deviations (`PARAMETERS`' names): from the undamped reduced system's
    inverse, and with the cameras held (its S_gg block alone), both scaled by the residuals' variance; and,
    with the level free, that of the level relative to the submerged points (`_level_to_bed`)."""
    r = fit.r
    eq = problem.normal_equations(fit.state, r)
    S, _, Vi = problem.reduced(eq, 0.0)
    w = _huber(r.norm(dim=-1), problem.huber)[1]
    dof = max(r.numel() - 6 * problem.n_img - 3 * problem.n_pts - len(problem.index), 1)
    scale = float((w * (r * r).sum(-1)).sum()) / dof
    names = [PARAMETERS[j] for j in problem.index]
    sigma = {n: float(v.clamp(min=0).sqrt()) for n, v in zip(names, S.marginal().diagonal() * scale)}
    held = {n: float(v.clamp(min=0).sqrt())
            for n, v in zip(names, torch.linalg.inv(S.Sgg).diagonal() * scale)}
    to_bed = _level_to_bed(problem, fit.state, eq, S, Vi)
    return sigma, held, None if to_bed is None else math.sqrt(max(to_bed * scale, 0.0))


def _level_to_bed(problem: _Problem, s: _State, eq: dict, S: _System, Vi: torch.Tensor) -> float | None:
    """The variance (up to the residuals' scale) of the surface's height over the submerged points less their
    mean height: the common offset of their depths, which neither the frame's height nor its drift between
    cameras moves, where the level alone with the cameras held leaves out how the cameras and the points
    trade with it (through a lens's distortion, loosely held heights). The points are eliminated from the
    system, so the functional f = e_level . x - m . p (m: the submerged points' z, averaged) has the variance
    a^T S^-1 a + m^T V^-1 m with a = e_level + B V^-1 m, B the cameras' and the parameters' coupling to the
    points (the covariance of x and p back-substituted). None without the level free or submerged points."""
    if 0 not in problem.index:
        return None
    surface = problem.surface(s.theta)
    wet = torch.nonzero(surface.depth(s.points) > 0)[:, 0]
    if not len(wet):
        return None
    dt, n_img = problem.dt, problem.n_img
    m = torch.zeros(problem.n_pts, 3, dtype=dt, device=s.points.device)
    m[wet, 2] = 1.0 / len(wet)
    Vm = (Vi @ m[:, :, None])[..., 0]  # [P, 3]
    a_c = torch.zeros(n_img, 6, dtype=dt, device=m.device).index_add_(
        0, problem.image, (eq["W"] @ Vm[problem.point][:, :, None])[..., 0])
    a_g = (eq["Wg"] @ Vm[:, :, None])[..., 0].sum(0)  # [G]
    where = s.points[wet, :2].mean(0)  # the tilted plane's height at the submerged points' middle
    a_g = a_g + torch.tensor([{0: 1.0, 1: float(where[0]), 2: float(where[1])}.get(j, 0.0)
                              for j in problem.index], dtype=dt, device=m.device)
    a = torch.cat([a_c.reshape(-1), a_g])
    return float(a @ S.solve(a) + (m * Vm).sum())


DENSE_MAX = 3000  # unknowns of the reduced system solved dense (500 cameras: a 72 MB matrix); more: sparse
PAIR_CHUNK = 1 << 20  # observation pairs gathered at a time into the camera pairs' blocks (about 0.5 GB)


class _Couples:
    """The pairs of observations of a common point, gathered by camera pair a chunk of points at a time:
    `gather(Y, W)` is, for each camera pair (a, b) in `pairs` [B, 2], minus the sum of Y_i W_j^T over the
    observations i by a and j by b of one point. The observation pairs are listed again for each chunk (never
    all at once); the camera pairs, each camera with itself among them (`diagonal` [I]), once."""

    def __init__(self, point: torch.Tensor, image: torch.Tensor, n_pts: int, n_img: int):
        self.point, self.image, self.n_img = point, image, n_img
        self.order = torch.argsort(point, stable=True)  # the observations by point
        counts = torch.bincount(point, minlength=n_pts)
        self.start = torch.cumsum(counts, 0) - counts
        self.counts = counts
        # chunks of whole points, each with at most PAIR_CHUNK pairs (or one point)
        work = torch.cumsum(counts * counts, 0)
        total = int(work[-1]) if len(work) else 0
        edges = torch.searchsorted(work, torch.arange(PAIR_CHUNK, max(total, PAIR_CHUNK), PAIR_CHUNK,
                                                      device=work.device), right=True)
        bounds = torch.unique(torch.cat([torch.zeros(1, dtype=edges.dtype, device=edges.device), edges,
                                         torch.tensor([n_pts], device=edges.device)]))
        self.chunks = [(int(a), int(b)) for a, b in itertools.pairwise(bounds) if b > a]
        keys = [torch.arange(n_img, device=point.device) * (n_img + 1)]  # (i, i): every camera's own block
        for a, b in self.chunks:
            i, j = self._pairs(a, b)
            keys.append(torch.unique(image[i] * n_img + image[j]))
        self.keys = torch.unique(torch.cat(keys))  # sorted
        self.pairs = torch.stack([self.keys // n_img, self.keys % n_img], 1)  # [B, 2]
        self.diagonal = torch.searchsorted(self.keys, torch.arange(n_img, device=point.device) * (n_img + 1))

    def _pairs(self, a: int, b: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The observation pairs (i, j) of points a..b-1: every ordered pair of one point's observations."""
        obs = self.order[self.start[a]: self.start[b - 1] + self.counts[b - 1]]
        k = self.counts[self.point[obs]]
        rep = torch.repeat_interleave(obs, k)  # each observation once per observation of its point
        first = self.start[self.point[rep]]
        within = (torch.arange(len(rep), device=obs.device)
                  - torch.repeat_interleave(torch.cumsum(k, 0) - k, k))
        return rep, self.order[first + within]

    def gather(self, Y: torch.Tensor, W: torch.Tensor) -> torch.Tensor:  # [M, 6, 3] twice -> [B, 6, 6]
        blocks = torch.zeros(len(self.keys), 6, 6, dtype=Y.dtype, device=Y.device)
        for a, b in self.chunks:
            i, j = self._pairs(a, b)
            at = torch.searchsorted(self.keys, self.image[i] * self.n_img + self.image[j])
            blocks.index_add_(0, at, -(Y[i] @ W[j].mT))
        return blocks


@dataclass
class _System:
    """The reduced system [[S_cc, S_cg], [S_cg^T, S_gg]]: the cameras' blocks (`_Couples`' pairs) and the
    free parameters' dense rows (None without them)."""

    couples: _Couples
    blocks: torch.Tensor  # [B, 6, 6]
    Scg: torch.Tensor | None  # [6I, G]
    Sgg: torch.Tensor | None  # [G, G]
    sparse: bool

    def _cameras(self):
        """S_cc: a dense [6I, 6I] tensor, or a SciPy CSC matrix."""
        n, (a, b) = self.couples.n_img, self.couples.pairs.T
        if not self.sparse:
            S = torch.zeros(n, n, 6, 6, dtype=self.blocks.dtype, device=self.blocks.device)
            S[a, b] = self.blocks
            return S.permute(0, 2, 1, 3).reshape(6 * n, 6 * n)
        import numpy as np
        import scipy.sparse

        six = np.arange(6)
        rows = (6 * a.cpu().numpy())[:, None, None] + six[None, :, None]
        cols = (6 * b.cpu().numpy())[:, None, None] + six[None, None, :]
        values = self.blocks.detach().cpu().numpy()
        shape = np.broadcast_shapes(rows.shape, cols.shape)
        return scipy.sparse.csc_matrix((values.ravel(), (np.broadcast_to(rows, shape).ravel(),
                                                         np.broadcast_to(cols, shape).ravel())),
                                       shape=(6 * n, 6 * n))

    def _solve_cameras(self, S, rhs: torch.Tensor) -> torch.Tensor:  # S_cc^-1 rhs, rhs [6I] or [6I, G]
        if not self.sparse:
            return torch.linalg.solve(S, rhs)
        import scipy.sparse.linalg

        lu = scipy.sparse.linalg.splu(S)
        return torch.as_tensor(lu.solve(rhs.detach().cpu().numpy()), dtype=rhs.dtype, device=rhs.device)

    def solve(self, rhs: torch.Tensor) -> torch.Tensor:
        """The system's solution for `rhs` [6I + G]: the cameras' part eliminated first (S_cg, G columns)."""
        S = self._cameras()
        n = S.shape[0]
        if self.Scg is None:
            return self._solve_cameras(S, rhs)
        both = self._solve_cameras(S, torch.column_stack([rhs[:n], self.Scg]))  # S_cc^-1 [r_c, S_cg]
        x_g = torch.linalg.solve(self.Sgg - self.Scg.T @ both[:, 1:], rhs[n:] - self.Scg.T @ both[:, 0])
        return torch.cat([both[:, 0] - both[:, 1:] @ x_g, x_g])

    def marginal(self) -> torch.Tensor:
        """[G, G]: the free parameters' block of the system's inverse (their covariance up to the scale)."""
        return torch.linalg.inv(self.Sgg - self.Scg.T @ self._solve_cameras(self._cameras(), self.Scg))


FREE = ("level", "slope", "lens")
PARAMETERS = ("level", "slope_x", "slope_y", "k1", "k2")  # the shared parameters `free` can adjust
FD_STEP = (1e-5, 1e-7, 1e-7, 1e-7, 1e-7)  # central differences (m, m/m, and the lens's): float64, smooth


def _free_index(free: tuple[str, ...], water: WaterSurface | None) -> list[int]:
    """Indices into `PARAMETERS` of the `free` ones; ValueError for a name not in `FREE`, or the water's
    without a plane to adjust."""
    strange = set(free) - set(FREE)
    if strange:
        raise ValueError(f"free parameters are {FREE}, got {sorted(strange)}")
    if {"level", "slope"} & set(free) and (water is None or water.curved):
        raise ValueError("only a plane water surface (no profile) can be adjusted")
    return (([0] if "level" in free else []) + ([1, 2] if "slope" in free else [])
            + ([3, 4] if "lens" in free else []))
