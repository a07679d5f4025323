"""The differentiable Lucas-Kanade layer: the paper's LM solver (Algorithm 1) in torch, with two backwards.

The forward runs exactly the iteration of ``nsflow_ros.core.solver`` at one level, batched over points;
the flow, the LM state and the damping are float64 whatever the maps' dtype (as in the NumPy solver).

Backward modes (:class:`BackwardMode`):

* ``IMPLICIT`` - the implicit function theorem at the converged u*, where F(D1, D2, u) = J(u)^T f(u) = 0:
  du*/dD = -(dF/du)^-1 dF/dD, with the exact 2x2 block of dF/du per point (autograd on one re-evaluation
  of F) and one vector-Jacobian product through F, so memory does not grow with the iterations. Points
  whose block is not positive definite get no gradient (``min_curvature``): training diverged without
  this test. LM may stop slightly off F = 0 (its Scharr J is not the exact derivative of its bilinear
  cost), and there the gradient is that of the nearby fixed point.
* ``UNROLL`` - the same iterations recorded by autograd (accept/reject and stopping as hard masks), for
  comparison.

Coarse to fine (:func:`lk_track_pyramid`) solves level by level as ``nsflow_ros.core.solver.track`` does.
With the IMPLICIT backward each level is differentiated at its own converged flow and its start is
detached, because a converged flow does not depend on its start (du*/du0 = 0): the coarse maps learn
only through a loss on the coarse levels' own results (``LKPyramidOutput.levels``).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import torch

from nsflow_ros.core.pyramid import Smoothing
from nsflow_ros.core.solver import Jacobian, LMConfig, window_centres
from nsflow_ros.train.data import inside
from nsflow_ros.train.errors import TrainError
from nsflow_ros.train.ops import pyramid, sample_windows, scharr_gradients

__all__ = [
    "BackwardMode",
    "LKOutput",
    "LKPyramidOutput",
    "Template",
    "lk_track",
    "lk_track_pyramid",
    "optimality_condition",
    "residual_and_jacobian",
    "stack_level",
    "template_windows",
]


class BackwardMode(enum.Enum):
    """How gradients flow back through the LK layer."""

    IMPLICIT = "implicit"
    UNROLL = "unroll"


@dataclass(frozen=True)
class LKOutput:
    """Result of :func:`lk_track`: the (N, 2) float64 flow u*, differentiable w.r.t. both maps; the (N,)
    status by the NumPy solver's rule, final cost 1/2 ||f||^2 (no gradient) and LM iterations."""

    flow: torch.Tensor
    status: torch.Tensor
    cost: torch.Tensor
    iterations: torch.Tensor


@dataclass(frozen=True)
class LKPyramidOutput:
    """Result of :func:`lk_track_pyramid`: level 0's flow, status and cost as in :class:`LKOutput`, the
    iterations summed over levels, and each level's :class:`LKOutput` (level 0 first, flow in level-0
    pixels)."""

    flow: torch.Tensor
    status: torch.Tensor
    cost: torch.Tensor
    iterations: torch.Tensor
    levels: tuple[LKOutput, ...]


def stack_level(desc: torch.Tensor) -> torch.Tensor:
    """[D | Dx | Dy] of a map: what the solver samples.

    Shape:
        desc: (C, H, W). Returns (3C, H, W).
    """
    dx, dy = scharr_gradients(desc)
    return torch.cat([desc, dx, dy], dim=0)


@dataclass(frozen=True)
class Template:
    """The frame-1 side of a solve: D1 over each point's window (M, C window^2), with ESM its x / y
    derivatives there (M, 2, C window^2), and whether residuals and Jacobians lose their window means."""

    values: torch.Tensor
    grad: torch.Tensor | None
    channels: int = 1
    zero_mean: bool = False

    def take(self, idx: torch.Tensor) -> Template:
        """The templates of the points ``idx``."""
        grad = None if self.grad is None else self.grad[idx]
        return Template(self.values[idx], grad, self.channels, self.zero_mean)

    def centred(self, a: torch.Tensor) -> torch.Tensor:
        """``a`` (M, C window^2) less its window mean per channel when ``zero_mean``, else ``a``."""
        if not self.zero_mean:
            return a
        b = a.reshape(a.shape[0], self.channels, -1)
        return (b - b.mean(dim=2, keepdim=True)).reshape(a.shape)


def template_windows(
    desc1: torch.Tensor, pts: torch.Tensor, window: int, jacobian: Jacobian, zero_mean: bool = False
) -> Template:
    """The frame-1 template at ``pts`` (with its derivatives for ESM).

    Shape:
        desc1: (C, H, W). pts: (M, 2).
    """
    n, c = pts.shape[0], desc1.shape[0]
    if jacobian is Jacobian.ESM:
        s = sample_windows(stack_level(desc1), pts, window).reshape(n, 3, -1)
        return Template(s[:, 0], s[:, 1:], c, zero_mean)
    return Template(sample_windows(desc1, pts, window).reshape(n, -1), None, c, zero_mean)


def residual_and_jacobian(
    level2: torch.Tensor, centers: torch.Tensor, template: Template, window: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """f = D2(x + u) - D1(x) and the step's J (x and y) at the frame-2 centres x + u.

    J is D2's Scharr derivative there, with an ESM template its mean with D1's at x.

    Shape:
        level2: (3C, H, W) from :func:`stack_level`. centers: (M, 2). Returns three (M, C window^2).
    """
    s = sample_windows(level2, centers, window).reshape(centers.shape[0], 3, -1)
    f = s[:, 0] - template.values
    if template.grad is None:
        jx, jy = s[:, 1], s[:, 2]
    else:
        jx, jy = 0.5 * (s[:, 1] + template.grad[:, 0]), 0.5 * (s[:, 2] + template.grad[:, 1])
    return template.centred(f), template.centred(jx), template.centred(jy)


def _normal_equations(
    level2: torch.Tensor, centers: torch.Tensor, template: Template, window: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """S (M,), J^T J as (h11, h12, h22) (M, 3) and J^T f (M, 2) at the frame-2 centres."""
    f, jx, jy = residual_and_jacobian(level2, centers, template, window)
    cost = 0.5 * (f * f).sum(1).double()
    hess = torch.stack([(jx * jx).sum(1), (jx * jy).sum(1), (jy * jy).sum(1)], 1).double()
    grad = torch.stack([(jx * f).sum(1), (jy * f).sum(1)], 1).double()
    return cost, hess, grad


def optimality_condition(
    desc1: torch.Tensor,
    desc2: torch.Tensor,
    points: torch.Tensor,
    flow: torch.Tensor,
    window: int,
    jacobian: Jacobian = Jacobian.FORWARD,
    zero_mean: bool = False,
) -> torch.Tensor:
    """F(D1, D2, u) = J(u)^T f(u) per point in the maps' dtype, zero at a converged solution of the solver.

    Shape:
        desc1, desc2: (C, H, W). points, flow: (N, 2). Returns (N, 2).
    """
    template = template_windows(desc1, points, window, jacobian, zero_mean)
    f, jx, jy = residual_and_jacobian(stack_level(desc2), points + flow, template, window)
    return torch.stack([(jx * f).sum(1), (jy * f).sum(1)], 1)


def _lm_solve(
    desc1: torch.Tensor, desc2: torch.Tensor, pts: torch.Tensor, u0: torch.Tensor, cfg: LMConfig
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Algorithm 1 at one level: (u, cost, hess, iterations), differentiable when grad is enabled.

    Results are written back out of place so that the same code records a valid graph in UNROLL mode.
    """
    win = cfg.window
    n = pts.shape[0]
    level2 = stack_level(desc2)
    template = template_windows(desc1, pts, win, cfg.jacobian, cfg.zero_mean)
    cost, hess, grad = _normal_equations(level2, pts + u0, template, win)
    u = u0
    lam = torch.full((n,), cfg.lambda_init, dtype=torch.float64, device=pts.device)
    if cfg.lambda_scale > 0:  # per-point lambda^(0) from J^T J, as in the NumPy solver
        lam = torch.maximum(lam, cfg.lambda_scale * torch.maximum(hess[:, 0], hess[:, 2]).detach())
    iterations = torch.zeros(n, dtype=torch.int64, device=pts.device)
    idx = torch.arange(n, device=pts.device)
    for _ in range(cfg.max_iterations):
        if idx.numel() == 0:
            break
        u_a, c_a, h_a, g_a, lam_a = u[idx], cost[idx], hess[idx], grad[idx], lam[idx]
        a11 = h_a[:, 0] + lam_a
        a22 = h_a[:, 2] + lam_a
        a12 = h_a[:, 1]
        det = a11 * a22 - a12 * a12
        du = -torch.stack([a22 * g_a[:, 0] - a12 * g_a[:, 1], a11 * g_a[:, 1] - a12 * g_a[:, 0]], 1)
        du = du / det[:, None]
        du = torch.where(torch.isfinite(du), du, torch.zeros_like(du))
        cand = u_a + du
        cc, ch, cg = _normal_equations(level2, pts[idx] + cand, template.take(idx), win)
        with torch.no_grad():
            accept = cc < c_a
            step_small = torch.linalg.vector_norm(du, dim=1) < cfg.eps * (
                1.0 + torch.linalg.vector_norm(u_a, dim=1)
            )
            grad_small = g_a.abs().amax(1) < cfg.eps
            stop = step_small | grad_small
        acc = accept[:, None]
        u = u.index_put((idx,), torch.where(acc, cand, u_a))
        cost = cost.index_put((idx,), torch.where(accept, cc, c_a))
        hess = hess.index_put((idx,), torch.where(acc, ch, h_a))
        grad = grad.index_put((idx,), torch.where(acc, cg, g_a))
        lam = lam.index_put((idx,), torch.where(accept, lam_a / cfg.nu, lam_a * cfg.nu).detach())
        iterations[idx] += 1
        idx = idx[~stop]
    return u, cost, hess, iterations


def _valid(
    pts: torch.Tensor,
    u: torch.Tensor,
    hess: torch.Tensor,
    shape: tuple[int, int],
    channels: int,
    cfg: LMConfig,
) -> torch.Tensor:
    """The NumPy solver's status rule: finite, both windows inside the image, textured window."""
    h, w = shape
    r = cfg.window // 2
    new = pts + u
    finite = torch.isfinite(new).all(1)
    tr = hess[:, 0] + hess[:, 2]
    diff = hess[:, 0] - hess[:, 2]
    min_eig = 0.5 * (tr - torch.sqrt(diff * diff + 4.0 * hess[:, 1] ** 2))
    textured = min_eig / (cfg.window**2 * channels) >= cfg.min_eigen
    safe_new = torch.where(finite[:, None], new, torch.full_like(new, -1e9))
    return finite & inside(pts, w, h, r) & inside(safe_new, w, h, r) & textured


class _ImplicitLK(torch.autograd.Function):
    """LM forward without a graph; implicit-function-theorem backward."""

    @staticmethod
    def forward(ctx, desc1, desc2, points, flow0, cfg, residual_tol, min_curvature):  # type: ignore[override]
        with torch.no_grad():
            u, cost, hess, iters = _lm_solve(desc1, desc2, points, flow0, cfg)
            status = _valid(points, u, hess, tuple(desc1.shape[1:]), desc1.shape[0], cfg)
        ctx.save_for_backward(desc1, desc2, points, u, status)
        ctx.window = cfg.window
        ctx.jacobian = cfg.jacobian
        ctx.zero_mean = cfg.zero_mean
        ctx.residual_tol = residual_tol
        ctx.min_curvature = min_curvature
        ctx.mark_non_differentiable(status, cost, iters)
        return u, status, cost, iters

    @staticmethod
    def backward(ctx, grad_u, *_unused):  # type: ignore[override]
        desc1, desc2, points, u, status = ctx.saved_tensors
        if grad_u is None:
            return None, None, None, None, None, None, None
        need1, need2 = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        with torch.enable_grad():
            d1 = desc1.detach().requires_grad_(need1)
            d2 = desc2.detach().requires_grad_(need2)
            uu = u.detach().requires_grad_(True)
            fval = optimality_condition(d1, d2, points, uu, ctx.window, ctx.jacobian, ctx.zero_mean)  # (N, 2)
            # Exact dF/du, block row by block row (F_i depends on u_i only).
            row0 = torch.autograd.grad(fval[:, 0].sum(), uu, retain_graph=True)[0]
            row1 = torch.autograd.grad(fval[:, 1].sum(), uu, retain_graph=True)[0]
            a00, a01 = row0[:, 0], row0[:, 1]
            a10, a11 = row1[:, 0], row1[:, 1]
            det = a00 * a11 - a01 * a10
            g = grad_u.to(torch.float64)
            # w = -(dF/du)^-T grad_u, closed form per 2x2 block.
            w0 = -(a11 * g[:, 0] - a10 * g[:, 1]) / det
            w1 = -(a00 * g[:, 1] - a01 * g[:, 0]) / det
            w = torch.stack([w0, w1], 1)
            ok = status & torch.isfinite(w).all(1) & (det.abs() > 0)
            if ctx.residual_tol is not None:  # the IFT holds only where F(u*) = 0
                ok &= fval.detach().abs().amax(1) <= ctx.residual_tol
            if ctx.min_curvature is not None:
                # A local minimum has a positive definite dF/du; elsewhere (-dF/du)^-1 is no slope.
                s12 = 0.5 * (a01 + a10)
                tr, df = a00 + a11, a00 - a11
                root = torch.sqrt(df * df + 4 * s12 * s12)
                lo, hi = 0.5 * (tr - root), 0.5 * (tr + root)
                ok &= lo > ctx.min_curvature * hi

            w = torch.where(ok[:, None], w, torch.zeros_like(w)).to(fval.dtype)
            inputs = [t for t, need in ((d1, need1), (d2, need2)) if need]
            grads = (
                list(torch.autograd.grad(fval, inputs, grad_outputs=w, allow_unused=True)) if inputs else []
            )
        gd1 = grads.pop(0) if need1 else None
        gd2 = grads.pop(0) if need2 else None
        return gd1, gd2, None, None, None, None, None


def _as_map(desc: torch.Tensor, name: str) -> torch.Tensor:
    if desc.dim() == 4:
        if desc.shape[0] != 1:
            raise TrainError(f"{name} must be (C, H, W) or (1, C, H, W), got {tuple(desc.shape)}")
        desc = desc[0]
    if desc.dim() != 3:
        raise TrainError(f"{name} must be (C, H, W) or (1, C, H, W), got {tuple(desc.shape)}")
    if not desc.is_floating_point():
        raise TrainError(f"{name} must be floating point, got {desc.dtype}")
    return desc


def _check_inputs(
    desc1: torch.Tensor,
    desc2: torch.Tensor,
    points: torch.Tensor,
    flow0: torch.Tensor | None,
    mode: BackwardMode,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(D1, D2, points, flow0) as (C, H, W) maps and float64 (N, 2) tensors without gradient."""
    d1 = _as_map(desc1, "desc1")
    d2 = _as_map(desc2, "desc2")
    if d1.shape != d2.shape:
        raise TrainError(f"descriptor maps differ: desc1 {tuple(d1.shape)}, desc2 {tuple(d2.shape)}")
    if d1.dtype != d2.dtype:
        raise TrainError(f"descriptor maps differ in dtype: {d1.dtype} vs {d2.dtype}")
    if points.dim() != 2 or points.shape[1] != 2:
        raise TrainError(f"points must have shape (N, 2), got {tuple(points.shape)}")
    n = points.shape[0]
    pts = points.detach().to(torch.float64)
    if flow0 is None:
        u0 = torch.zeros((n, 2), dtype=torch.float64, device=pts.device)
    else:
        if tuple(flow0.shape) != (n, 2):
            raise TrainError(f"flow0 must have shape ({n}, 2) like points, got {tuple(flow0.shape)}")
        u0 = flow0.detach().to(torch.float64)
    if not (torch.isfinite(pts).all() and torch.isfinite(u0).all()):
        raise TrainError("points and flow0 must be finite")
    if not isinstance(mode, BackwardMode):
        raise TrainError(f"mode must be a BackwardMode, got {mode!r}")
    return d1, d2, pts, u0


def _track_level(
    d1: torch.Tensor,
    d2: torch.Tensor,
    pts: torch.Tensor,
    u0: torch.Tensor,
    cfg: LMConfig,
    mode: BackwardMode,
    residual_tol: float | None,
    min_curvature: float | None,
) -> LKOutput:
    """Algorithm 1 on one level with the chosen backward (``cfg.levels`` is ignored)."""
    if mode is BackwardMode.IMPLICIT:
        u, status, cost, iters = _ImplicitLK.apply(d1, d2, pts, u0, cfg, residual_tol, min_curvature)
        return LKOutput(u, status, cost, iters)
    u, cost, hess, iters = _lm_solve(d1, d2, pts, u0, cfg)
    status = _valid(pts, u.detach(), hess.detach(), tuple(d1.shape[1:]), d1.shape[0], cfg)
    return LKOutput(u, status, cost.detach(), iters)


def lk_track(
    desc1: torch.Tensor,
    desc2: torch.Tensor,
    points: torch.Tensor,
    flow0: torch.Tensor | None = None,
    config: LMConfig | None = None,
    mode: BackwardMode = BackwardMode.IMPLICIT,
    residual_tol: float | None = None,
    min_curvature: float | None = 0.0,
) -> LKOutput:
    """Track points from frame 1 to frame 2 with the LM-LK solver, differentiably w.r.t. both maps.

    Args:
        desc1: frame-1 descriptor map (e.g. the encoder output).
        desc2: frame-2 descriptor map, same shape.
        points: keypoints x in frame 1, (x, y) pixels.
        flow0: initial flow (zeros when None); it receives no gradient.
        config: single-level solver settings; ``LMConfig(levels=1)`` when None.
        mode: the backward.
        residual_tol: IMPLICIT only: points whose ||F(u*)||_inf exceeds this get no gradient (the theorem
            holds only at a stationary point); None = every tracked point gets one.
        min_curvature: IMPLICIT only: a point gets a gradient only if the symmetric part of its dF/du
            block is positive definite with eigenvalue ratio min/max above this (elsewhere the implicit
            slope points nowhere useful and can be huge); None = no test.

    Returns:
        an :class:`LKOutput`; ``flow`` matches ``nsflow_ros.track(..., LMConfig(levels=1, ...))``.

    Raises:
        TrainError: on mismatched maps, wrong point/flow shapes, or a multi-level config.

    Shape:
        desc1, desc2: (C, H, W) or (1, C, H, W). points, flow0: (N, 2).
    """
    cfg = config or LMConfig(levels=1)
    if cfg.levels != 1:
        raise TrainError(
            f"lk_track is single-scale: config.levels must be 1, got {cfg.levels} (see lk_track_pyramid)"
        )
    d1, d2, pts, u0 = _check_inputs(desc1, desc2, points, flow0, mode)
    return _track_level(d1, d2, pts, u0, cfg, mode, residual_tol, min_curvature)


def lk_track_pyramid(
    desc1: torch.Tensor,
    desc2: torch.Tensor,
    points: torch.Tensor,
    flow0: torch.Tensor | None = None,
    config: LMConfig | None = None,
    mode: BackwardMode = BackwardMode.IMPLICIT,
    residual_tol: float | None = None,
    min_curvature: float | None = 0.0,
    smoothing: Smoothing | None = None,
) -> LKPyramidOutput:
    """Track coarse to fine through the descriptor pyramid, as ``nsflow_ros.track`` does, differentiably.

    Args are those of :func:`lk_track` (full-resolution maps, per level), ``config`` holding the levels
    (``LMConfig()`` when None) and ``smoothing`` the pyramid's (:func:`nsflow_ros.train.ops.pyramid`).
    ``flow`` matches ``nsflow_ros.track(..., config)`` on pyramids built with the same smoothing.

    Raises:
        TrainError: on mismatched maps or wrong point/flow shapes.

    Shape:
        desc1, desc2: (C, H, W) or (1, C, H, W). points, flow0: (N, 2).
    """
    cfg = config or LMConfig()
    d1, d2, pts, u0 = _check_inputs(desc1, desc2, points, flow0, mode)
    pyr1 = pyramid(d1, cfg.levels, smoothing)
    pyr2 = pyramid(d2, cfg.levels, smoothing)
    nlev = len(pyr1)
    u = u0 / 2.0 ** (nlev - 1)
    outputs: list[LKOutput] = []
    iterations = torch.zeros(pts.shape[0], dtype=torch.int64, device=pts.device)
    for lev in range(nlev - 1, -1, -1):
        s = 2.0**lev
        start = u.detach() if mode is BackwardMode.IMPLICIT else u
        # a coarse level's windows are moved inside it as the core moves them (points carry no gradient)
        p_l = pts / s
        if lev:
            at = window_centres(p_l.detach().cpu().numpy(), tuple(pyr1[lev].shape[-2:]), cfg.window_at(lev))
            p_l = torch.from_numpy(at).to(p_l)
        res = _track_level(
            pyr1[lev], pyr2[lev], p_l, start, cfg.at_level(lev), mode, residual_tol, min_curvature
        )
        iterations = iterations + res.iterations
        outputs.append(LKOutput(res.flow * s, res.status, res.cost, res.iterations))
        u = res.flow * 2.0
    final = outputs[-1]
    return LKPyramidOutput(final.flow, final.status, final.cost, iterations, tuple(reversed(outputs)))
