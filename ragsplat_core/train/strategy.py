"""Adaptive density control (3DGS's clone / split / prune / opacity reset) as a strategy object, gsplat style.

The trainer owns the parameters (`ParameterDict`) and one Adam per parameter (`dict[name, Optimizer]`);
the strategy keeps its own running state in a plain dict and is called twice per step:

    state = strategy.initialize_state(scene_scale)
    ... render, loss ...
    strategy.step_pre_backward(params, optimizers, state, step, info)   # keeps the 2-D mean gradient
    loss.backward()
    strategy.step_post_backward(params, optimizers, state, step, info)  # accumulates, grows, prunes, resets

`info` is the rasterizer's meta dict with `means2d` ([N, 2] pixel centres that are in the autograd
graph), `radii` ([N], > 0 where the Gaussian touched the image), `width` and `height`. Under water these are
the APPARENT Gaussians' projections, which is what the image gradient sees; the row i of every parameter
is the same Gaussian before and after the transform, so growing and pruning act on the true Gaussians.

Every op edits the parameters and the matching Adam moments together, so a Gaussian that is cloned,
split, pruned or reset keeps (or, for new ones, starts from zero) its own optimiser state.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch

from ragsplat.gaussians import PARAM_NAMES, quat_to_rotmat

PAPER_ITERATIONS = 30_000  # the schedule below is 3DGS's, written for this many iterations


@dataclass(frozen=True)
class DensifyConfig:
    """3DGS defaults (iterations as for a 30k-iteration run; use `scaled` for another length)."""

    prune_opa: float = 0.005  # prune below this opacity
    grow_grad2d: float = 0.0002  # grow where the mean 2-D gradient (NDC units) exceeds this
    grow_scale3d: float = 0.01  # clone if max scale <= this x scene scale, else split
    prune_scale3d: float = 0.1  # prune larger than this x scene scale (after the first reset)
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    reset_every: int = 3_000
    refine_every: int = 100
    split_samples: int = 2
    max_gaussians: int = 0  # 0: unbounded; else growth stops at this count (highest gradients first)

    def scaled(self, iterations: int, min_refine_every: int = 10) -> DensifyConfig:
        """The same schedule stretched to `iterations` (refinement at least every `min_refine_every` steps,
        so each refinement still averages gradients over several views)."""
        f = iterations / PAPER_ITERATIONS

        def s(it: int) -> int:
            return max(1, round(it * f))

        return replace(self, refine_start_iter=s(self.refine_start_iter),
                       refine_stop_iter=s(self.refine_stop_iter), reset_every=s(self.reset_every),
                       refine_every=max(min_refine_every, s(self.refine_every)))


@torch.no_grad()
def _update(params: torch.nn.ParameterDict, optimizers: dict, param_fn: Callable, state_fn: Callable) -> None:
    """Replace every parameter by `param_fn(name, p)` and each Adam moment by `state_fn(name, key, v)`."""
    for name in list(params.keys()):
        old = params[name]
        new = torch.nn.Parameter(param_fn(name, old.data), requires_grad=old.requires_grad)
        params[name] = new
        opt = optimizers[name]
        moments = opt.state.pop(old, {})
        for key, v in moments.items():
            if key != "step" and torch.is_tensor(v) and v.shape == old.shape:
                moments[key] = state_fn(name, key, v)
        opt.param_groups[0]["params"] = [new]
        if moments:
            opt.state[new] = moments


def _filter_state(state: dict, keep: torch.Tensor, grow: int = 0) -> None:
    """Per-Gaussian running state: keep rows `keep` (bool [N]) and append `grow` zero rows."""
    for key in ("grad2d", "count"):
        v = state.get(key)
        if v is not None:
            state[key] = torch.cat([v[keep], v.new_zeros(grow)])


@torch.no_grad()
def duplicate(params, optimizers, state: dict, mask: torch.Tensor) -> int:
    """Clone the Gaussians in `mask` (bool [N]): copies appended at the end, fresh (zero) Adam moments."""
    sel = torch.where(mask)[0]
    _update(params, optimizers, lambda _, p: torch.cat([p, p[sel]]),
            lambda _, __, v: torch.cat([v, v.new_zeros((len(sel),) + v.shape[1:])]))
    _filter_state(state, torch.ones_like(mask), len(sel))
    return len(sel)


@torch.no_grad()
def split(params, optimizers, state: dict, mask: torch.Tensor, samples: int = 2, generator=None) -> int:
    """Replace each Gaussian in `mask` by `samples` children drawn from it, scales / 1.6 (3DGS)."""
    sel = torch.where(mask)[0]
    rest = torch.where(~mask)[0]
    scales = torch.exp(params["scales"][sel])  # [S, 3]
    rot = quat_to_rotmat(params["quats"][sel])  # [S, 3, 3]
    noise = torch.randn((samples, len(sel), 3), generator=generator, dtype=scales.dtype, device="cpu")
    offsets = torch.einsum("nij,nj,bnj->bni", rot, scales, noise.to(scales.device))  # [B, S, 3]
    shrink = math.log(0.8 * samples)  # 3DGS: children's scales = parent / (0.8 N)

    def child(name: str, p: torch.Tensor) -> torch.Tensor:
        if name == "means":
            kids = (p[sel] + offsets).reshape(-1, 3)
        elif name == "scales":
            kids = (p[sel] - shrink).repeat(samples, 1)
        else:
            kids = p[sel].repeat((samples,) + (1,) * (p.dim() - 1))
        return torch.cat([p[rest], kids])

    _update(params, optimizers, child,
            lambda _, __, v: torch.cat([v[rest], v.new_zeros((samples * len(sel),) + v.shape[1:])]))
    _filter_state(state, ~mask, samples * len(sel))
    return len(sel)


@torch.no_grad()
def remove(params, optimizers, state: dict, mask: torch.Tensor) -> int:
    """Delete the Gaussians in `mask` (bool [N]) together with their Adam moments."""
    keep = ~mask
    _update(params, optimizers, lambda _, p: p[keep], lambda _, __, v: v[keep])
    _filter_state(state, keep)
    return int(mask.sum())


@torch.no_grad()
def reset_opacity(params, optimizers, value) -> None:
    """Clamp opacities to at most `value` (a number, or one per Gaussian [N] in (0, 1)) and zero their Adam
    moments (the other parameters are untouched)."""
    cap = math.log(value / (1 - value)) if isinstance(value, float) else torch.log(value / (1 - value))
    _update(params, optimizers,
            lambda name, p: p.clamp_max(cap) if name == "opacities" else p,
            lambda name, _, v: torch.zeros_like(v) if name == "opacities" else v)


class DefaultStrategy:
    """3DGS adaptive density control driven by the accumulated 2-D mean gradient."""

    def __init__(self, cfg: DensifyConfig = DensifyConfig(), generator: torch.Generator | None = None,
                 opacity_factor: Callable | None = None):
        self.cfg = cfg
        self.generator = generator  # CPU generator for the split samples (reproducible runs)
        # means [N, 3] -> [N] rendered / true opacity (RA-GS: 1 / n^2 under water). Pruning and resets test
        # what is rendered: a Gaussian the rasterizer skips (below 1/255) gets no gradient, so a threshold on
        # the true opacity would leave it frozen, neither trained nor pruned. None: they are the same.
        self.opacity_factor = opacity_factor

    def initialize_state(self, scene_scale: float = 1.0) -> dict:
        return {"grad2d": None, "count": None, "scene_scale": float(scene_scale)}

    def check_sanity(self, params: torch.nn.ParameterDict, optimizers: dict) -> None:
        missing = [k for k in PARAM_NAMES[:5] if k not in params]
        if missing:
            raise ValueError(f"parameters missing {missing}")
        if set(params.keys()) != set(optimizers.keys()):
            raise ValueError(f"one optimiser per parameter needed: {sorted(params.keys())} vs "
                             f"{sorted(optimizers)}")

    def step_pre_backward(self, params, optimizers, state: dict, step: int, info: dict) -> None:
        # gsplat's backend hands a detached tensor whose .grad it fills itself; the others need retain_grad
        if step < self.cfg.refine_stop_iter and info["means2d"].requires_grad:
            info["means2d"].retain_grad()

    @torch.no_grad()
    def step_post_backward(self, params, optimizers, state: dict, step: int, info: dict) -> dict:
        """Accumulate gradients; on refinement steps grow and prune; reset opacities on schedule.

        Returns counts of what happened this step (empty dict when nothing did) for logging.
        """
        cfg = self.cfg
        if step >= cfg.refine_stop_iter:
            return {}
        self._accumulate(params, state, info)
        out = {}
        if step > cfg.refine_start_iter and step % cfg.refine_every == 0:
            out["cloned"], out["split"] = self._grow(params, optimizers, state)
            out["pruned"] = self._prune(params, optimizers, state, step)
            state["grad2d"].zero_()
            state["count"].zero_()
        if step % cfg.reset_every == 0 and step > 0:
            value = 2.0 * cfg.prune_opa
            if self.opacity_factor is not None:  # rendered at most `value`
                value = (value / self.opacity_factor(params["means"])).clamp_max(0.5)
            reset_opacity(params, optimizers, value)
            out["reset"] = 1
        return out

    def _accumulate(self, params, state: dict, info: dict) -> None:
        n = params["means"].shape[0]
        dev = params["means"].device
        if state["grad2d"] is None:
            state["grad2d"] = torch.zeros(n, device=dev)
            state["count"] = torch.zeros(n, device=dev)
        grad = info["means2d"].grad
        if grad is None:  # nothing on screen contributed
            return
        # Pixels -> NDC units, as 3DGS and gsplat threshold them.
        scale = grad.new_tensor([info["width"] / 2.0, info["height"] / 2.0])
        norms = (grad * scale).norm(dim=-1).float()  # [N]
        seen = info["radii"] > 0
        state["grad2d"] += torch.where(seen, norms, torch.zeros_like(norms))
        state["count"] += seen.float()

    def _grow(self, params, optimizers, state: dict) -> tuple[int, int]:
        cfg = self.cfg
        avg = state["grad2d"] / state["count"].clamp_min(1)
        high = avg > cfg.grow_grad2d
        if cfg.max_gaussians:
            room = cfg.max_gaussians - params["means"].shape[0]
            if room <= 0:
                return 0, 0
            if int(high.sum()) > room:  # keep the strongest candidates (a split adds one net Gaussian too)
                top = torch.topk(torch.where(high, avg, torch.zeros_like(avg)), room).indices
                high = torch.zeros_like(high)
                high[top] = True
        small = torch.exp(params["scales"]).max(-1).values <= cfg.grow_scale3d * state["scene_scale"]
        n_clone = duplicate(params, optimizers, state, high & small)
        grow_split = torch.cat([high & ~small, high.new_zeros(n_clone)])
        n_split = split(params, optimizers, state, grow_split, cfg.split_samples, self.generator)
        return n_clone, n_split

    def _prune(self, params, optimizers, state: dict, step: int) -> int:
        cfg = self.cfg
        rendered = torch.sigmoid(params["opacities"])
        if self.opacity_factor is not None:
            rendered = rendered * self.opacity_factor(params["means"])
        prune = rendered < cfg.prune_opa
        if step > cfg.reset_every:
            prune |= torch.exp(params["scales"]).max(-1).values > cfg.prune_scale3d * state["scene_scale"]
        if bool(prune.all()):  # never delete the whole scene: keep the most opaque Gaussian
            prune[torch.argmax(params["opacities"])] = False
        return remove(params, optimizers, state, prune) if bool(prune.any()) else 0
