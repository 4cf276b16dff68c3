import math

import pytest
import torch

from ragsplat.gaussians import init_grid, quat_to_rotmat
from ragsplat.train.strategy import (
    DefaultStrategy,
    DensifyConfig,
    duplicate,
    remove,
    reset_opacity,
    split,
)


def _setup(n_side=4, seed=0):
    torch.manual_seed(seed)
    params = init_grid(0, n_side, 0, n_side, -1.0, 1.0, degree=1, opacity=0.5, dtype=torch.float64)
    with torch.no_grad():
        for p in params.values():
            p.add_(0.01 * torch.randn_like(p))
    opts = {k: torch.optim.Adam([{"params": [p], "lr": 1e-3, "name": k}], eps=1e-15)
            for k, p in params.items()}
    _step(params, opts)  # populate Adam moments
    return params, opts


def _step(params, opts):
    loss = sum((p**2).sum() for p in params.values())  # a different gradient for every row
    for o in opts.values():
        o.zero_grad()
    loss.backward()
    for o in opts.values():
        o.step()


def _moments(opts, name):
    st = opts[name].state[opts[name].param_groups[0]["params"][0]]
    return st["exp_avg"], st["exp_avg_sq"]


def _check_consistent(params, opts):
    for k, p in params.items():
        group = opts[k].param_groups[0]["params"]
        assert len(group) == 1 and group[0] is p
        assert set(opts[k].state.keys()) == {p}
        m, v = _moments(opts, k)
        assert m.shape == p.shape and v.shape == p.shape


def test_duplicate_keeps_and_zeroes_moments():
    params, opts = _setup()
    old = {k: p.detach().clone() for k, p in params.items()}
    old_m = {k: _moments(opts, k)[0].clone() for k in params}
    mask = torch.zeros(16, dtype=torch.bool)
    mask[[2, 5, 11]] = True
    state = {"grad2d": torch.arange(16.0), "count": torch.ones(16)}
    assert duplicate(params, opts, state, mask) == 3
    _check_consistent(params, opts)
    for k in params:
        assert torch.equal(params[k][:16], old[k]) and torch.equal(params[k][16:], old[k][mask])
        m, v = _moments(opts, k)
        assert torch.equal(m[:16], old_m[k]) and not m[16:].any() and not v[16:].any()
    assert torch.equal(state["grad2d"], torch.cat([torch.arange(16.0), torch.zeros(3)]))
    _step(params, opts)  # the optimiser still works on the new tensors
    _check_consistent(params, opts)


def test_split_children():
    params, opts = _setup()
    old = {k: p.detach().clone() for k, p in params.items()}
    old_m = _moments(opts, "means")[0].clone()
    mask = torch.zeros(16, dtype=torch.bool)
    mask[[0, 7]] = True
    g = torch.Generator().manual_seed(3)
    assert split(params, opts, {}, mask, samples=2, generator=g) == 2
    _check_consistent(params, opts)
    n_rest = 14
    assert params["means"].shape[0] == n_rest + 4
    assert torch.equal(params["means"][:n_rest], old["means"][~mask])
    assert torch.equal(_moments(opts, "means")[0][:n_rest], old_m[~mask])
    assert not _moments(opts, "means")[0][n_rest:].any()
    # children: [sample0 of parent0, sample0 of parent7, sample1 of parent0, sample1 of parent7]
    parents = old["means"][mask].repeat(2, 1)
    assert torch.allclose(params["scales"][n_rest:], old["scales"][mask].repeat(2, 1) - math.log(1.6))
    assert torch.equal(params["sh0"][n_rest:], old["sh0"][mask].repeat(2, 1, 1))
    # offsets are samples of the parent Gaussian: whitened, they are O(1) and not all zero
    rot = quat_to_rotmat(old["quats"][mask]).repeat(2, 1, 1)
    local = torch.einsum("nji,nj->ni", rot, params["means"][n_rest:] - parents)
    whitened = local / torch.exp(old["scales"][mask]).repeat(2, 1)
    assert 0 < whitened.abs().max() < 6


def test_remove_and_reset():
    params, opts = _setup()
    old = {k: p.detach().clone() for k, p in params.items()}
    old_v = _moments(opts, "scales")[1].clone()
    mask = torch.zeros(16, dtype=torch.bool)
    mask[3:6] = True
    state = {"grad2d": torch.arange(16.0), "count": torch.ones(16)}
    assert remove(params, opts, state, mask) == 3
    _check_consistent(params, opts)
    assert torch.equal(params["means"], old["means"][~mask])
    assert torch.equal(_moments(opts, "scales")[1], old_v[~mask])
    assert torch.equal(state["grad2d"], torch.arange(16.0)[~mask])
    reset_opacity(params, opts, 0.01)
    _check_consistent(params, opts)
    assert float(torch.sigmoid(params["opacities"].detach()).max()) == pytest.approx(0.01)
    assert not _moments(opts, "opacities")[0].any()
    assert torch.equal(_moments(opts, "scales")[1], old_v[~mask])  # others untouched


def _info(n, grads, radii=None):
    means2d = torch.zeros(n, 2, dtype=torch.float64, requires_grad=True)
    means2d.grad = grads
    return {"means2d": means2d, "radii": torch.ones(n) if radii is None else radii, "width": 2, "height": 2}


def test_strategy_grows_and_prunes():
    params, opts = _setup()
    with torch.no_grad():
        params["scales"][:8] = math.log(0.01)  # small -> clone
        params["scales"][8:] = math.log(0.5)  # large -> split
        params["opacities"][15] = -10.0  # prune
    cfg = DensifyConfig(refine_start_iter=0, refine_every=2, reset_every=1000, refine_stop_iter=100,
                        grow_grad2d=0.5, grow_scale3d=0.1, prune_scale3d=10.0)
    strat = DefaultStrategy(cfg, torch.Generator().manual_seed(0))
    state = strat.initialize_state(scene_scale=1.0)
    strat.check_sanity(params, opts)
    grads = torch.zeros(16, 2, dtype=torch.float64)
    grads[[1, 9], 0] = 1.0  # with width/2 = 1 the NDC gradient norm is 1 > 0.5
    radii = torch.ones(16)
    radii[2] = 0
    grads[2, 0] = 5.0  # off screen: not counted
    assert strat.step_post_backward(params, opts, state, 1, _info(16, grads, radii)) == {}
    out = strat.step_post_backward(params, opts, state, 2, _info(16, grads, radii))
    assert out == {"cloned": 1, "split": 1, "pruned": 1}
    assert params["means"].shape[0] == 16 + 1 + 1 - 1
    _check_consistent(params, opts)
    assert state["grad2d"].shape == (17,) and not state["grad2d"].any() and not state["count"].any()


def test_strategy_cap_and_reset_and_stop():
    params, opts = _setup()
    cfg = DensifyConfig(refine_start_iter=0, refine_every=1, reset_every=3, refine_stop_iter=5,
                        grow_grad2d=0.0, grow_scale3d=100.0, prune_opa=0.001, max_gaussians=20)
    strat = DefaultStrategy(cfg)
    state = strat.initialize_state()
    grads = torch.rand(16, 2, dtype=torch.float64) + 0.1
    out = strat.step_post_backward(params, opts, state, 1, _info(16, grads))
    assert out["cloned"] == 4 and params["means"].shape[0] == 20  # capped
    out = strat.step_post_backward(params, opts, state, 3, _info(20, torch.ones(20, 2, dtype=torch.float64)))
    assert out["cloned"] == 0 and out["reset"] == 1
    assert float(torch.sigmoid(params["opacities"].detach()).max()) <= 0.002 + 1e-12
    assert (strat.step_post_backward(params, opts, state, 5,
                                     _info(20, torch.ones(20, 2, dtype=torch.float64))) == {})


def test_never_prunes_everything():
    params, opts = _setup()
    with torch.no_grad():
        params["opacities"].fill_(-20.0)
        params["opacities"][4] = -19.0
    strat = DefaultStrategy(DensifyConfig(refine_start_iter=0, refine_every=1, grow_grad2d=1e9))
    state = strat.initialize_state()
    strat.step_post_backward(params, opts, state, 1, _info(16, torch.zeros(16, 2, dtype=torch.float64)))
    assert params["means"].shape[0] == 1 and float(params["opacities"].detach()[0]) == -19.0


def test_schedule_scaling():
    cfg = DensifyConfig().scaled(3000)
    assert ((cfg.refine_start_iter, cfg.refine_stop_iter, cfg.reset_every, cfg.refine_every)
            == (50, 1500, 300, 10))
    assert DensifyConfig().scaled(30_000) == DensifyConfig()
    assert DensifyConfig().scaled(300).refine_every == 10


def test_split_is_reproducible_under_a_generator():
    outs = []
    for _ in range(2):
        params, opts = _setup(seed=1)
        split(params, opts, {}, torch.ones(16, dtype=torch.bool), generator=torch.Generator().manual_seed(9))
        outs.append(params["means"].detach().clone())
    assert torch.equal(outs[0], outs[1])  # same function, same inputs and seed, one process: bit-identical


def test_pruning_and_resets_test_the_rendered_opacity():
    """The dead zone: under water a Gaussian renders at alpha / n^2; at true opacity 0.006 that is 0.0034,
    below the rasterizer's 1/255, so it gets no gradient. With the water's opacity factor the strategy prunes
    it (and a dry Gaussian of the same opacity stays); a reset leaves every Gaussian rendering at
    2 x prune_opa, submerged or not."""
    from ragsplat.refraction import opacity_factor
    from ragsplat.water_surface import WaterSurface

    water = WaterSurface(level=0.0, n=1.33)
    params, opts = _setup()  # a 4 x 4 grid at z = -1: submerged
    with torch.no_grad():
        params["means"][8:, 2] = 0.5  # the second half dry
        params["opacities"][[0, 8]] = math.log(0.006 / (1 - 0.006))
    assert 0.006 / 1.33**2 < 1 / 255 < 0.006
    cfg = DensifyConfig(refine_start_iter=0, refine_every=1, reset_every=1000, grow_grad2d=1e9)
    grads = torch.zeros(16, 2, dtype=torch.float64)
    for factor, pruned in ((None, 0), (lambda m: opacity_factor(m, water), 1)):
        p, o = {k: torch.nn.Parameter(v.detach().clone()) for k, v in params.items()}, None
        p = torch.nn.ParameterDict(p)
        o = {k: torch.optim.Adam([{"params": [v], "lr": 1e-3, "name": k}], eps=1e-15) for k, v in p.items()}
        strat = DefaultStrategy(cfg, opacity_factor=factor)
        out = strat.step_post_backward(p, o, strat.initialize_state(), 1, _info(16, grads))
        assert out["pruned"] == pruned  # with the factor: the submerged one only (the dry one renders 0.006)
    reset = DensifyConfig(refine_start_iter=100, reset_every=2, prune_opa=0.005)
    strat = DefaultStrategy(reset, opacity_factor=lambda m: opacity_factor(m, water))

    def rendered():
        return torch.sigmoid(params["opacities"].detach()) * opacity_factor(params["means"].detach(), water)

    expected = rendered().clamp_max(0.01)  # a reset only lowers: the two faint ones stay as they were
    strat.step_post_backward(params, opts, strat.initialize_state(), 2, _info(16, grads))
    torch.testing.assert_close(rendered(), expected)
    assert int((expected == 0.01).sum()) == 14  # clamp_max returns the bound itself
