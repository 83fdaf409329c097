"""Densification and pruning (agg/train/densify.py): clone / split / prune decisions, the Gaussian-count and scale
caps, optimiser-state surgery, the ``src`` row map, a real fit, and bit-exact resume from ``state_dict``.

Adam convention checked here: kept rows keep their moments, new rows (clones and both split children) start at zero.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from agg.nodes.gaussians import PARAM_NAMES, GaussianParams
from agg.render import rasterize
from agg.train.densify import Densifier, DensifyConfig
from tests.render_scenes import look_K, random_scene

EXTENT = 10.0
IMG = 100  # width = height of the fake renders fed to accumulate: grad px * 50 = normalised grad
HIGH, LOW = 1e-5, 1e-6  # px gradients -> normalised 5e-4 (above 2e-4) and 5e-5 (below)
LR = {"means": 0.01, "log_scales": 0.02, "quats": 0.01, "opacity_logits": 0.05, "sh": 0.02}


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny tensors and images: one thread is fastest, and spinning OpenMP threads on a busy machine are slow."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def make_params(means, scales, opacities, quats=None, sh_degree=0, seed=0) -> GaussianParams:
    """Rows at ``means`` [N, 3] with per-axis ``scales`` [N, 3] (or [N] isotropic) and ``opacities`` [N]."""
    means = torch.as_tensor(means, dtype=torch.float32).reshape(-1, 3)
    n = means.shape[0]
    scales = torch.as_tensor(scales, dtype=torch.float32)
    scales = scales[:, None].repeat(1, 3) if scales.ndim == 1 else scales
    opac = torch.as_tensor(opacities, dtype=torch.float32)
    q = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1) if quats is None else torch.as_tensor(quats).float()
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=torch.Generator().manual_seed(seed))
    return GaussianParams(means, scales.log(), q, torch.log(opac / (1 - opac)), sh)


def feed(d: Densifier, key: str, grads, radius=3.0, visible=None) -> None:
    """One fake render: px gradient norms ``grads`` [N] along x, screen radius ``radius`` px ([N] or scalar)."""
    grads = torch.as_tensor(grads, dtype=torch.float32)
    n = grads.numel()
    g2 = torch.stack([grads, torch.zeros(n)], -1)
    radii = torch.as_tensor(radius, dtype=torch.float32).expand(n)[:, None].repeat(1, 2).round().int()
    vis = torch.ones(n, dtype=torch.bool) if visible is None else torch.as_tensor(visible)
    d.accumulate(key, g2, radii, vis, IMG, IMG)


def cfg(**kw) -> DensifyConfig:
    base = dict(refine_start=0, refine_stop=1000, refine_every=10, reset_every=0, size_prune_start=0,
                min_gaussians_to_keep=0, max_gaussians=10_000)
    base.update(kw)
    return DensifyConfig(**base)


def test_scaled_multiplies_every_milestone():
    c = DensifyConfig(grad_threshold=3e-4, max_gaussians=123)
    s = c.scaled(0.1)
    assert (s.refine_start, s.refine_stop, s.refine_every, s.reset_every, s.size_prune_start) == (50, 1500, 10, 300,
                                                                                                  300)
    assert (s.grad_threshold, s.max_gaussians, s.split_scale) == (3e-4, 123, c.split_scale)
    assert c.scaled(1e-4).refine_every == 1  # periods never reach 0
    assert [i for i in range(0, 200) if s.is_refine(i)] == list(range(60, 200, 10))
    assert [i for i in range(0, 700) if s.is_reset(i)] == [300, 600]
    with pytest.raises(ValueError):
        DensifyConfig(oversize="grow")


def test_clone_small_and_split_large_by_mean_gradient():
    # rows: 0 small high-grad, 1 large high-grad, 2 small low-grad, 3 large low-grad,
    #       4 small with a high gradient SUM over 4 renders but a low MEAN (not grown), 5 high-grad but invisible
    means = torch.arange(18, dtype=torch.float32).reshape(6, 3)
    p = make_params(means, [0.05, 0.5, 0.05, 0.5, 0.05, 0.05], [0.5] * 6)
    old = p.state()
    d = Densifier(cfg(), EXTENT)  # split above 0.01 * 10 = 0.1
    feed(d, "bg", [HIGH, HIGH, LOW, LOW, 2e-6, HIGH], visible=[True] * 5 + [False])
    for _ in range(3):
        feed(d, "bg", [0, 0, 0, 0, 2e-6, HIGH], visible=[False] * 4 + [True, False])
    assert torch.allclose(d.mean_grad("bg")[:5], torch.tensor([5e-4, 5e-4, 5e-5, 5e-5, 1e-4]))
    assert d.step("bg", p, None, 9) is None and len(p) == 6  # not a refine iteration
    src = d.step("bg", p, None, 10)
    assert src.tolist() == [0, 2, 3, 4, 5, 0, 1, 1]  # kept rows, the clone of 0, the two children of 1
    assert len(p) == 8 and d.last["bg"] == {"iteration": 10, "cloned": 1, "split": 1, "pruned": 0, "before": 6,
                                             "after": 8}
    # kept rows and the clone are exact copies of their source rows
    for name in PARAM_NAMES:
        assert torch.equal(getattr(p, name)[:6].detach(), old[name][src[:6]]), name
    # split children: parent's rotation / opacity / colour, scales / 1.6, means sampled around the parent
    kids = p.means[6:].detach()
    assert torch.allclose(p.log_scales[6:].exp(), torch.full((2, 3), 0.5 / 1.6))
    for name in ("quats", "opacity_logits", "sh"):
        assert torch.equal(getattr(p, name)[6:].detach(), old[name][[1, 1]]), name
    offsets = kids - old["means"][1]
    assert not torch.equal(kids[0], kids[1]) and float(offsets.norm(dim=-1).max()) < 5 * 0.5 * math.sqrt(3)
    # statistics are reset (to the new size) after a refine
    assert torch.equal(d.mean_grad("bg"), torch.zeros(8))


def test_split_children_follow_the_parent_covariance():
    n = 4000
    half = math.radians(30) / 2
    q = torch.tensor([[math.cos(half), 0.0, 0.0, math.sin(half)]]).repeat(n, 1)  # 30 deg about z
    s = torch.tensor([[0.3, 0.1, 0.05]]).repeat(n, 1)
    p = make_params(torch.zeros(n, 3), s, [0.5] * n, quats=q)
    d = Densifier(cfg(), EXTENT)
    feed(d, "bg", [HIGH] * n)
    src = d.step("bg", p, None, 10)
    assert len(p) == 2 * n and torch.equal(src, torch.arange(n).repeat(2))
    c, sn = math.cos(2 * half), math.sin(2 * half)
    axes = torch.tensor([[c, sn, 0.0], [-sn, c, 0.0], [0.0, 0.0, 1.0]])  # rows: the parent's local axes in world
    local = p.means.detach() @ axes.T  # [2n, 3] offsets in the parent frame
    std = local.std(0)
    assert torch.allclose(std, s[0], rtol=0.05), std
    corr = torch.corrcoef(local.T)
    assert float((corr - torch.eye(3)).abs().max()) < 0.05
    assert torch.allclose(p.log_scales.exp(), (s[0] / 1.6).expand(2 * n, 3))


def test_prune_transparent_oversize_and_screen_large():
    # rows: 0 transparent, 1 oversize (2.0 > 0.1 * 10), 2 large on screen, 3..5 normal
    def fresh():
        p = make_params(torch.randn(6, 3), [0.05, 2.0, 0.05, 0.05, 0.05, 0.05], [0.001, 0.5, 0.5, 0.5, 0.5, 0.5])
        return p, p.state()

    for it, size_start, expect in ((10, 10, [1, 2, 3, 4, 5]), (20, 10, [3, 4, 5])):
        p, old = fresh()
        d = Densifier(cfg(size_prune_start=size_start), EXTENT)
        feed(d, "bg", [0.0] * 6, radius=[3, 3, 30, 3, 3, 3])  # 30 px / 100 px = 0.3 > 0.15
        src = d.step("bg", p, None, it)
        assert src.tolist() == expect and torch.equal(p.means.detach(), old["means"][expect])
        assert d.last["bg"]["pruned"] == 6 - len(expect)
    # clamp mode keeps the oversize row at max_scale x extent
    p, old = fresh()
    d = Densifier(cfg(oversize="clamp", max_screen_fraction=None), EXTENT)
    feed(d, "bg", [0.0] * 6)
    assert d.step("bg", p, None, 20).tolist() == [1, 2, 3, 4, 5]
    assert torch.allclose(p.log_scales[0].exp(), torch.full((3,), 1.0))
    # after refine_stop nothing is added or removed, but scales are still clamped
    p, old = fresh()
    d = Densifier(cfg(refine_stop=100), EXTENT)
    feed(d, "bg", [HIGH] * 6)
    assert d.step("bg", p, None, 110) is None and len(p) == 6
    assert torch.allclose(p.log_scales.exp().amax(-1), torch.tensor([0.05, 1.0, 0.05, 0.05, 0.05, 0.05]))


def test_min_gaussians_to_keep_per_group():
    opac = [0.001, 0.002, 0.003, 0.004, 0.0045, 0.5, 0.5, 0.001, 0.5, 0.5]
    groups = torch.tensor([0, 0, 0, 0, 0, 1, 1, 1, 1, 1])  # group 0 fully transparent
    p = make_params(torch.randn(10, 3), [0.05] * 10, opac)
    d = Densifier(cfg(min_gaussians_to_keep=2), EXTENT)
    src = d.step("agents", p, None, 10, groups=groups)
    assert src.tolist() == [3, 4, 5, 6, 8, 9]  # group 0 keeps its two most opaque rows, group 1 prunes normally
    p = make_params(torch.randn(10, 3), [0.05] * 10, [0.001] * 10)
    d = Densifier(cfg(min_gaussians_to_keep=3), EXTENT)
    assert len(d.step("bg", p, None, 10)) == 3 and len(p) == 3  # never pruned to zero


def test_cap_keeps_highest_gradients_and_trims_least_opaque():
    n = 50
    grads = torch.linspace(1, 2, n) * HIGH
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(0))
    p = make_params(torch.randn(n, 3), [0.05] * n, [0.5] * n)
    d = Densifier(cfg(max_gaussians=80), EXTENT)
    feed(d, "bg", grads[perm])
    src = d.step("bg", p, None, 10)
    assert len(p) == 80 and d.last["bg"]["cloned"] == 30
    top30 = torch.sort(torch.argsort(grads[perm], descending=True)[:30]).values
    assert torch.equal(src[n:], top30)
    # above the cap already (e.g. a big initialisation): the least opaque rows go, nothing grows
    opac = torch.linspace(0.1, 0.9, 100)[torch.randperm(100, generator=torch.Generator().manual_seed(1))]
    p = make_params(torch.randn(100, 3), [0.05] * 100, opac)
    d = Densifier(cfg(max_gaussians=60), EXTENT)
    feed(d, "bg", [HIGH] * 100)
    src = d.step("bg", p, None, 10)
    assert len(p) == 60 and torch.equal(src, torch.sort(torch.argsort(opac, descending=True)[:60]).values)


def _adam_with_moments(p: GaussianParams, steps: int = 3) -> torch.optim.Adam:
    opt = torch.optim.Adam(p.param_groups("bg", LR))
    g = torch.Generator().manual_seed(3)
    weights = {n: torch.randn(getattr(p, n).shape, generator=g).to(getattr(p, n)) for n in PARAM_NAMES}
    for _ in range(steps):
        opt.zero_grad()
        sum((getattr(p, n) * weights[n]).sum() for n in PARAM_NAMES).backward()
        opt.step()
    return opt


def test_adam_state_follows_rows_and_new_rows_start_at_zero():
    n = 12
    scales = [0.05, 0.5] * 6
    opac = [0.5] * 10 + [0.001, 0.001]  # the last two are pruned
    grads = [HIGH] * 4 + [LOW] * 8  # rows 0, 2 cloned, rows 1, 3 split
    p = make_params(torch.randn(n, 3), scales, opac, sh_degree=1)
    opt = _adam_with_moments(p)
    before = {nm: {k: v.clone() for k, v in opt.state[getattr(p, nm)].items()} for nm in PARAM_NAMES}
    d = Densifier(cfg(), EXTENT)
    feed(d, "bg", grads)
    src = d.step("bg", p, opt, 10)
    kept = n - 2 - 2  # originals left: minus 2 pruned, minus 2 split parents
    assert len(p) == kept + 2 + 4 and src[:kept].tolist() == [0, 2, 4, 5, 6, 7, 8, 9]
    for nm in PARAM_NAMES:
        param = getattr(p, nm)
        assert any(param is q for grp in opt.param_groups for q in grp["params"]), nm
        state = opt.state[param]
        for k in ("exp_avg", "exp_avg_sq"):
            assert state[k].shape == param.shape
            assert torch.equal(state[k][:kept], before[nm][k][src[:kept]]), (nm, k)
            assert torch.count_nonzero(state[k][kept:]) == 0, (nm, k)
            assert torch.count_nonzero(before[nm][k][src[:kept]]) > 0
        assert torch.equal(state["step"], before[nm]["step"])
    # the optimiser keeps working on the new rows
    means_before = p.means.detach().clone()
    opt.zero_grad()
    (p.means.sum() + p.opacity_logits.sum()).backward()
    opt.step()
    assert torch.all(p.means.detach() != means_before)


def test_opacity_reset_clamps_and_zeroes_opacity_moments():
    p = make_params(torch.randn(8, 3), [0.05] * 8, [0.9, 0.5, 0.2, 0.005, 0.009, 0.011, 0.3, 0.7])
    opt = _adam_with_moments(p)
    old = torch.sigmoid(p.opacity_logits.detach()).clone()
    means_avg = opt.state[p.means]["exp_avg"].clone()
    d = Densifier(cfg(refine_every=7, reset_every=30), EXTENT)
    assert d.step("bg", p, opt, 30) is None  # a reset, not a refine iteration
    new = torch.sigmoid(p.opacity_logits.detach())
    assert torch.allclose(new, old.clamp_max(0.01), atol=1e-6)
    assert torch.count_nonzero(opt.state[p.opacity_logits]["exp_avg"]) == 0
    assert torch.count_nonzero(opt.state[p.opacity_logits]["exp_avg_sq"]) == 0
    assert torch.equal(opt.state[p.means]["exp_avg"], means_avg)


def test_src_carries_per_row_buffers():
    n = 300
    g = torch.Generator().manual_seed(5)
    scales = torch.exp(torch.empty(n).uniform_(math.log(0.02), math.log(0.5), generator=g))
    opac = torch.empty(n).uniform_(0.0, 0.2, generator=g).clamp_min(1e-4)
    instance = torch.randint(0, 6, (n,), generator=g)
    p = make_params(torch.randn(n, 3, generator=g), scales, opac, sh_degree=1)
    old = p.state()
    d = Densifier(cfg(min_gaussians_to_keep=4, max_gaussians=380, prune_opacity=0.05), EXTENT)
    feed(d, "rigid", torch.empty(n).uniform_(0, 2 * HIGH, generator=g))
    src = d.step("rigid", p, None, 10, groups=instance)
    last = d.last["rigid"]
    assert last["cloned"] > 0 and last["split"] > 0 and last["pruned"] > 0 and len(p) == len(src) <= 380
    new_instance = instance[src]
    assert set(new_instance.tolist()) == set(range(6))
    n_kids = 2 * last["split"]
    same = slice(0, len(p) - n_kids)  # kept rows and clones: exact copies of their source rows
    for name in PARAM_NAMES:
        assert torch.equal(getattr(p, name)[same].detach(), old[name][src[same]]), name
    kids = slice(len(p) - n_kids, len(p))
    assert torch.allclose(p.log_scales[kids].detach(), old["log_scales"][src[kids]] - math.log(1.6))
    assert torch.equal(p.sh[kids].detach(), old["sh"][src[kids]])
    dist = (p.means[kids].detach() - old["means"][src[kids]]).norm(dim=-1)
    assert bool((dist < 6 * old["log_scales"][src[kids]].exp().amax(-1)).all())


def test_statistics_accumulate_remap_and_forget(caplog):
    d = Densifier(cfg(), EXTENT)
    feed(d, "bg", [HIGH, LOW, 2 * HIGH])
    d.accumulate("bg", None, torch.full((3, 2), 3), torch.tensor([True, False, False]), IMG, IMG)  # no gradient
    assert torch.allclose(d.mean_grad("bg"), torch.tensor([2.5e-4, 5e-5, 1e-3]))
    d.accumulate("bg", torch.tensor([[0.0, 0.0], [0.0, 0.0], [1e-5, 0.0]]), torch.full((3, 2), 3),
                 torch.ones(3, dtype=torch.bool), IMG, IMG, renders=4)  # a loss averaged over 4 renders
    assert torch.allclose(d.mean_grad("bg"), torch.tensor([1e-3 / 6, 2.5e-5, 1.5e-3]))
    d.remap("bg", torch.tensor([2, -1, 0]))  # a row change made elsewhere: new row 1 has no parent
    assert torch.allclose(d.mean_grad("bg"), torch.tensor([1.5e-3, 0.0, 1e-3 / 6]))
    feed(d, "bg", [HIGH] * 5)  # rows changed without remap: statistics restart, with a warning
    assert "statistics reset" in caplog.text and torch.allclose(d.mean_grad("bg"), torch.full((5,), 5e-4))
    d.forget("bg")
    assert d.mean_grad("bg") is None


# --------------------------------------------------------------------------------------------------- real fits
W, H = 64, 48
FIT_CFG = DensifyConfig(grad_threshold=2e-4, refine_start=20, refine_stop=250, refine_every=10, reset_every=100,
                        split_scale=0.02, max_gaussians=500, size_prune_start=100, min_gaussians_to_keep=4)


def _target():
    gt = {k: v.detach() for k, v in random_scene(400, 7, channels=3, scale_range=(0.03, 0.15)).items()}
    with torch.no_grad():
        img = rasterize(gt["means"], gt["quats"], gt["scales"], gt["opacities"], gt["colors"], K=look_K(W, H),
                        width=W, height=H, viewmat=gt["viewmat"], background=torch.zeros(3), backend="cpu").color
    return img, gt["viewmat"]


def _too_few(n: int = 16) -> GaussianParams:
    g = torch.Generator().manual_seed(1)
    z = torch.empty(n).uniform_(3.0, 7.0, generator=g)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * z[:, None]
    xyz = torch.cat([xy, z[:, None]], -1).numpy()
    return GaussianParams.from_points(xyz, np.full((n, 3), 0.5), sh_degree=0, opacity=0.5, scales=np.full(n, 0.4))


def _render(p: GaussianParams, view):
    a = p.activated()
    return rasterize(a["means"], a["quats"], a["scales"], a["opacities"], sh=a["sh"], K=look_K(W, H), width=W,
                     height=H, viewmat=view, background=torch.zeros(3), backend="cpu")


def _train(p, opt, d, target, view, start, stop, sizes=None):
    for it in range(start, stop + 1):
        out = _render(p, view)
        out.meta.means2d.retain_grad()
        loss = (out.color - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if d is not None:
            d.accumulate("bg", out.meta.means2d.grad, out.meta.radii, out.meta.visible, W, H)
            d.step("bg", p, opt, it)
        if sizes is not None:
            sizes.append(len(p))


def _psnr(p, target, view) -> float:
    with torch.no_grad():
        return float(-10 * torch.log10(((_render(p, view).color - target) ** 2).mean()))


def test_densification_raises_psnr_of_a_fit_from_too_few_gaussians():
    target, view = _target()
    results = {}
    for densify in (False, True):
        p = _too_few()
        opt = torch.optim.Adam(p.param_groups("bg", LR))
        sizes = []
        _train(p, opt, Densifier(FIT_CFG, 5.0) if densify else None, target, view, 1, 300, sizes)
        results[densify] = (_psnr(p, target, view), max(sizes))
    (plain, n_plain), (dense, n_dense) = results[False], results[True]
    assert n_plain == 16 and 100 < n_dense <= FIT_CFG.max_gaussians
    assert dense > plain + 8.0, results  # measured: 18.2 dB -> 35.1 dB


def test_state_dict_round_trip_resumes_bit_exactly(tmp_path):
    target, view = _target()
    cfg_ = FIT_CFG.scaled(0.4)  # refines every 4 iterations from 8 to 100, resets at 40 and 80

    def start():
        p = _too_few()
        return p, torch.optim.Adam(p.param_groups("bg", LR)), Densifier(cfg_, 5.0)

    p, opt, d = start()
    _train(p, opt, d, target, view, 1, 50)
    torch.save({"params": p.state(), "opt": opt.state_dict(), "densify": d.state_dict()}, tmp_path / "ckpt.pt")
    _train(p, opt, d, target, view, 51, 90)
    reference, reference_gen = p.state(), d.generator.get_state()

    def resume(reseed: int | None):
        ckpt = torch.load(tmp_path / "ckpt.pt")  # weights_only loading is enough
        p2 = GaussianParams.from_state(ckpt["params"])
        opt2 = torch.optim.Adam(p2.param_groups("bg", LR))
        opt2.load_state_dict(ckpt["opt"])
        d2 = Densifier(cfg_, 5.0)
        d2.load_state_dict(ckpt["densify"])
        if reseed is not None:
            d2.generator.manual_seed(reseed)
        _train(p2, opt2, d2, target, view, 51, 90)
        return p2.state(), d2.generator.get_state(), ckpt["densify"]["generator"]

    resumed, resumed_gen, ckpt_gen = resume(None)
    assert not torch.equal(ckpt_gen, reference_gen)  # splits happened after the checkpoint
    assert torch.equal(resumed_gen, reference_gen)
    assert all(torch.equal(resumed[k], reference[k]) for k in PARAM_NAMES)
    other, _, _ = resume(123)  # the split generator's state matters: without it the run diverges
    assert not all(other[k].shape == reference[k].shape and torch.equal(other[k], reference[k]) for k in PARAM_NAMES)


@pytest.mark.cuda
def test_step_on_cuda_matches_cpu():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    n = 400
    g = torch.Generator().manual_seed(9)
    scales = torch.exp(torch.empty(n).uniform_(math.log(0.02), math.log(0.5), generator=g))
    opac = torch.empty(n).uniform_(0.0, 0.2, generator=g).clamp_min(1e-4)
    grads = torch.empty(n).uniform_(0, 2 * HIGH, generator=g)
    base = make_params(torch.randn(n, 3, generator=g), scales, opac, sh_degree=1)
    out = {}
    for device in ("cpu", "cuda"):
        p = GaussianParams.from_state({k: v.to(device) for k, v in base.state().items()})
        opt = _adam_with_moments(p)
        d = Densifier(cfg(max_gaussians=450, prune_opacity=0.05), EXTENT)
        d.accumulate("bg", torch.stack([grads, torch.zeros(n)], -1).to(device),
                     torch.full((n, 2), 3, dtype=torch.int32, device=device),
                     torch.ones(n, dtype=torch.bool, device=device), IMG, IMG)
        src = d.step("bg", p, opt, 10)
        out[device] = (src.cpu(), {k: v.cpu() for k, v in p.state().items()},
                       opt.state[p.means]["exp_avg"].cpu())
    assert torch.equal(out["cpu"][0], out["cuda"][0])
    for k in PARAM_NAMES:
        assert torch.allclose(out["cpu"][1][k], out["cuda"][1][k], atol=1e-5), k
    assert torch.allclose(out["cpu"][2], out["cuda"][2], atol=1e-6)
