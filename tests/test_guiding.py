"""Guided boundary sampling: the guides' densities, and unbiasedness of every combination
(grid/kdtree × light/dir/mis × edge sorting) against the unguided estimator."""
import copy
import itertools

import mitsuba as mi
import numpy as np
import pytest

from psdr_cli import api
from psdr_cli.config.options import with_estimator
from psdr_cli.estimators.sample_log import SampleLog, thinned
from psdr_cli.experiment.load import parse_experiment
from psdr_cli.guiding import auto, build_grid, build_kdtree
from psdr_cli.guiding.guide import GuideStats, trilinear_weights
from psdr_cli.guiding.kdtree import KdTreeGuide, TreeLimits
from psdr_cli.guiding.loop_fed import fitted_guides
from psdr_cli.guiding.targets import Guides
from psdr_cli.rendering.estimate import forward_gradient, make_guides, prepare

R = 24


def peaked(u):
    """A sparse, discontinuous test target: a narrow bump beyond u1 = 0.4 plus a step."""
    bump = np.exp(-((u[:, 1] - 0.3) ** 2 + (u[:, 2] - 0.7) ** 2) / 0.005) * (u[:, 0] > 0.4)
    return bump + 0.1 * (u[:, 0] < 0.2)


@pytest.fixture(scope="module")
def variant():
    from psdr_cli.support import backend
    return backend.select_variant("auto")


@pytest.mark.parametrize("kind", ["grid", "kdtree"])
def test_guide_pdf_normalised_and_matches_samples(variant, kind):
    guide = (build_grid(peaked, (16, 8, 8), 8, 0.05, seed=1) if kind == "grid"
             else build_kdtree(peaked, [0.2, 0.4, 0.7], limits=TreeLimits(32, 0.002), epsilon=0.05, seed=1,
                               initial_samples=4096))
    rng = np.random.default_rng(2)
    # ∫ g = 1: mean of g at uniform points
    p = guide.pdf_np(rng.random((200_000, 3)))
    assert abs(p.mean() - 1.0) < 4 * p.std() / np.sqrt(len(p))
    # sampler and lookups agree on the density of every drawn point (Dr.Jit and numpy)
    s, ps = guide.sample_np(200_000, rng)
    assert s.min() >= 0 and s.max() < 1
    np.testing.assert_allclose(ps, guide.pdf_np(s), rtol=1e-3)
    # leaf histogram: counts per leaf follow ε·volume + (1 − ε)·mass/M (chi-square)
    counts = np.bincount(guide.leaf_of_np(s), minlength=len(guide.mass))
    vol = np.prod(guide.hi - guide.lo, axis=1)
    expected = len(s) * (guide.epsilon * vol + (1 - guide.epsilon) * guide.mass / guide.total)
    m = expected > 20
    chi2, dof = (((counts - expected) ** 2 / expected)[m]).sum(), m.sum()
    assert chi2 < dof + 5 * np.sqrt(2 * dof), (chi2, dof)
    # and the guided estimate of ∫F̃ is right
    f = peaked(s) / ps
    truth = 0.2 * 0.1 + 0.6 * np.pi * 0.005 * 0.998  # step + (almost all of) the Gaussian bump
    assert abs(f.mean() - truth) < 4 * f.std() / np.sqrt(len(f))


def test_trilinear_leaf_sampling_matches_density(variant):
    """Inside one leaf, samples follow the trilinear density (8×8×8 histogram vs exact bins)."""
    corners = np.array([[0.1, 2.0, 0.5, 1.0, 3.0, 0.0, 1.5, 0.7]])
    axis, split, child, leaf = (np.array([-1]), np.zeros(1), np.array([-1]), np.array([0]))
    guide = KdTreeGuide(np.zeros((1, 3)), np.ones((1, 3)), corners, 0.0, GuideStats("kdtree"),
                        (axis, split, child, leaf))
    rng = np.random.default_rng(3)
    s, ps = guide.sample_np(400_000, rng)
    b = np.minimum((s * 8).astype(int), 7)
    hist = np.bincount(b[:, 0] + 8 * b[:, 1] + 64 * b[:, 2], minlength=512) / len(s)
    # exact bin masses by a 4-point-per-axis Gauss rule (exact for trilinear functions)
    g, _ = np.polynomial.legendre.leggauss(2)
    q = (np.arange(8)[:, None] + 0.5 + 0.5 * g[None]) / 8  # (8, 2) nodes per bin
    i, j, k = np.meshgrid(np.arange(8), np.arange(8), np.arange(8), indexing="ij")
    pts = np.stack(np.broadcast_arrays(q[i][..., :, None, None], q[j][..., None, :, None],
                                       q[k][..., None, None, :]), -1).reshape(8, 8, 8, 8, 3)
    dens = guide.pdf_np(pts.reshape(-1, 3)).reshape(8, 8, 8, 8).mean(-1) / 512
    expected = dens.transpose(2, 1, 0).ravel()  # bin id = i + 8 j + 64 k
    z = (hist - expected) / np.sqrt(expected / len(s))
    assert np.abs(z).max() < 5, np.abs(z).max()
    assert abs(np.einsum("nc,nc->n", trilinear_weights(np.full((1, 3), 0.5)), corners)[0] / corners.mean() - 1) < 1e-12


def shadow_scene():
    """The direct-term validation scene of test_direct_boundary at R × R, θ = x-translation."""
    from test_direct_boundary import SHADOW as base
    data = copy.deepcopy(base)
    data["seed"] = 5
    data["scene"]["film"] = {"width": R, "height": R}
    data["parameter"] = {"object": "occ", "kind": "translate", "axis": [1, 0, 0]}
    data["estimator"] = {"spp": 4, "boundary_spp": 256, "kdtree": {"initial_samples": 49152}}
    return data


SHADOW = shadow_scene()

#: A glossy (flat-shaded, 300-face) bunny under a sky environment, rotated about z.
ENVMAP = {
    "name": "envmap", "seed": 4,
    "scene": {
        "film": {"width": R, "height": R}, "max_depth": 2,
        "cameras": [{"origin": [0.3, -2.2, 1.1], "target": [0, 0, 0.3], "fov": 35}],
        "emitters": [{"type": "sky", "sun_direction": [0.6, -0.3, 0.75], "turbidity": 3, "sun_scale": 0.0,
                      "sky_scale": 1.0}],
        "objects": [{"name": "bunny", "mesh": {"shape": "bunny", "size": 0.8, "faces": 300},
                     "bsdf": {"type": "principled", "base_color": [0.8, 0.6, 0.4], "roughness": 0.3,
                              "metallic": 0.2}},
                    {"name": "floor", "mesh": {"shape": "plane", "size": 6},
                     "bsdf": {"type": "diffuse", "reflectance": 0.5}, "edges": False}]},
    "parameter": {"object": "bunny", "kind": "rotate", "axis": [0, 0, 1]},
    "estimator": {"spp": 4, "boundary_spp": 1024, "kdtree": {"initial_samples": 49152}}}

PASSES = 16


BLOCKS = 3


def block_sums(image):
    """Sums of the (R, R, 3) image over BLOCKS × BLOCKS tiles, flattened."""
    b = R // BLOCKS
    return image.sum(-1).reshape(BLOCKS, b, BLOCKS, b).sum(axis=(1, 3)).ravel()


def direct_sums(tmp_path, data, passes, term="direct", motion=False, **overrides):
    """Block sums of ``term`` per pass, shape (passes, BLOCKS²); ``motion``: the guides' direct
    target includes the velocity (built with the scalar θ, as ``psdr grad`` does)."""
    exp = parse_experiment(copy.deepcopy(data), tmp_path / f"{data['name']}.yaml", cwd=tmp_path)
    exp = with_estimator(exp, **overrides)
    scene, parameter, edges, settings = prepare(exp)
    guides = make_guides(scene, edges, [0], (term,), settings, parameter if motion else None)
    est = forward_gradient(scene, edges, parameter, 0, term, settings, passes, guides=guides)
    scale = len(est.passes) * np.array(est.weights)[:, None]
    return np.array([block_sums(p) for p in est.passes]) * scale, guides


def mean_se(x):
    return x.mean(0), x.std(0, ddof=1) / np.sqrt(len(x))


COMBOS = list(itertools.product(["grid", "kdtree"], ["light", "dir", "mis"], [False, True]))


@pytest.mark.slow
@pytest.mark.parametrize("scene", [SHADOW, ENVMAP], ids=["shadow", "envmap"])
def test_guided_agrees_with_unguided(tmp_path, scene):
    """Every guiding × sampling × sorting combination estimates the same direct-term image.

    Compared on 3 × 3 tile sums (the whole-image sum of a translation gradient nearly cancels):
    12 combinations × 9 tiles; |z| < 4.5 keeps the family-wise false-alarm rate near 0.1 % for
    Gaussian errors, and the tiles carrying the signal have standard errors of a few percent of
    it, so a bias of ~10–20 % in any of them fails."""
    reference = {}
    for t in ("light", "dir", "mis"):
        reference[t] = mean_se(direct_sums(tmp_path, scene, 2 * PASSES, sampling=t, guiding="none")[0])
    # the unguided techniques agree with each other
    m0, s0 = reference["mis"]
    for t in ("light", "dir"):
        m, s = reference[t]
        assert (np.abs(m - m0) <= 4.5 * np.hypot(s, s0)).all(), (t, m, s, m0, s0)
    failures = []
    for guiding, sampling, sort in COMBOS:
        sums, guides = direct_sums(tmp_path, scene, PASSES, sampling=sampling, guiding=guiding, edge_sort=sort)
        assert guides.get("direct") and all(g.total > 0 for g in guides["direct"].values())
        m, s = mean_se(sums)
        z = (m - m0) / np.maximum(np.hypot(s, s0), 1e-12)
        k = np.argmax(np.abs(m0))
        print(f"{scene['name']} {guiding} {sampling} sort={sort}: strongest tile {m[k]:.4g} ± {s[k]:.2g} vs "
              f"{m0[k]:.4g} ± {s0[k]:.2g}; max |z| {np.abs(z).max():.2f}")
        if np.abs(z).max() >= 4.5:
            failures.append((guiding, sampling, sort, m.round(3), s.round(3), z.round(2)))
    assert not failures, failures


@pytest.mark.slow
@pytest.mark.parametrize("scene", [SHADOW, ENVMAP], ids=["shadow", "envmap"])
def test_motion_guided_agrees_with_unguided(tmp_path, scene):
    """Kd-tree guides whose target includes the velocity (forward mode, max_RGB |dv/dθ|) and, for
    MIS, the techniques' shared edge profile, estimate the same direct-term image as unguided MIS
    (3 × 3 tile sums, |z| < 4.5)."""
    m0, s0 = mean_se(direct_sums(tmp_path, scene, 2 * PASSES, sampling="mis", guiding="none")[0])
    for sampling, sort in itertools.product(["dir", "mis"], [False, True]):
        sums, guides = direct_sums(tmp_path, scene, PASSES, motion=True, sampling=sampling, guiding="kdtree",
                                   edge_sort=sort)
        assert guides.get("direct") and all(g.total > 0 for g in guides["direct"].values())
        m, s = mean_se(sums)
        z = (m - m0) / np.maximum(np.hypot(s, s0), 1e-12)
        assert np.abs(z).max() < 4.5, (sampling, sort, m.round(3), s.round(3), z.round(2))


#: A camera translated in x over a floor shadow cast from high up: the occluder (out of view)
#: is nearer the area light than the floor, so the segment x^D → x^S turns about the fixed source
#: point and passes the edge at λ = t_S/(t_S + t_D) ≈ 0.45 of the pixel-tied x^D's speed. The
#: shadow is the image's only edge (primary term 0): interior + direct must match FD.
CAMERA_SHADOW = {
    "name": "camera_shadow", "seed": 2,
    "scene": {
        "film": {"width": R, "height": R}, "max_depth": 2,
        "cameras": [{"origin": [0, -2.0, 0.8], "target": [0, 0, 0], "fov": 30}],
        "emitters": [{"type": "area", "center": [0.0, 0.4, 2.2], "normal": [0, 0, -1], "size": [0.5, 0.5],
                      "radiance": 20}],
        "objects": [{"name": "occ", "mesh": {"shape": "cube", "size": [0.4, 0.4, 0.1]},
                     "transform": {"translate": [0, 0.25, 1.2]}, "bsdf": {"type": "diffuse", "reflectance": 0.5}},
                    {"name": "floor", "mesh": {"shape": "plane", "size": 20},
                     "bsdf": {"type": "diffuse", "reflectance": 0.8}}]},
    "parameter": {"camera": 0, "kind": "translate", "axis": [1, 0, 0]},
    "estimator": {"spp": 16, "primary_spp": 16, "boundary_spp": 256, "kdtree": {"initial_samples": 65536}}}


@pytest.fixture(scope="module")
def camera_shadow(tmp_path_factory):
    """(experiment, unguided estimate, FD batches) of :data:`CAMERA_SHADOW`."""
    from psdr_cli.rendering.reference import finite_difference
    tmp = tmp_path_factory.mktemp("camera_shadow")
    exp = parse_experiment(copy.deepcopy(CAMERA_SHADOW), tmp / "camera_shadow.yaml", cwd=tmp)
    unguided = api.gradient_images(with_estimator(exp, guiding="none"), min_passes=8)
    scene, parameter, _, _ = prepare(exp)
    fd = finite_difference(scene, parameter, 0, 0.003, 4096, seed=1, batches=8)
    return exp, unguided, fd


@pytest.mark.slow
@pytest.mark.parametrize("guiding", ["grid", "kdtree"])
def test_moving_camera_guided_agrees_with_unguided_and_fd(camera_shadow, guiding):
    """A moving camera (forward mode, velocity in the direct term's target): the guided direct term
    agrees with the unguided one (3 × 3 tiles, |z| < 4.5), and both totals agree with FD (the
    verdict of ``psdr grad --fd`` on 4 × 4 tiles). Before the direct term's lever λ the direct term
    was 2.3× too large here (unguided max |z| 8.8, grid 35, Kd-tree 37 against FD), while guided
    and unguided agreed with each other: the bias was common to both and only the lower variance
    of the guided estimates made it visible on the camera-translation scene of
    tests/test_real_mesh_gradients.py."""
    from psdr_cli.rendering.reference import agreement, mean_and_error
    from psdr_cli.support.verdict import agrees, describe
    exp, unguided, fd = camera_shadow
    guided = api.gradient_images(with_estimator(exp, guiding=guiding), min_passes=8)
    (m0, s0), (m, s) = (mean_and_error([block_sums(p) for p in e["direct"].passes], e["direct"].weights)
                        for e in (unguided, guided))
    z = (m - m0) / np.maximum(np.hypot(s, s0), 1e-12)
    assert np.abs(m0).max() > 6 * s0[np.argmax(np.abs(m0))]  # the comparison has power
    assert np.abs(z).max() < 4.5, (m.round(2), s.round(2), m0.round(2), s0.round(2))
    failures = []
    for name, est in (("none", unguided), (guiding, guided)):
        stats = agreement([(e.passes, e.weights) for e in est.values()], fd, block=R // 4)
        if not agrees(stats):
            failures.append(f"{name}:\n{describe(stats)}")
    assert not failures, "\n".join(failures)


def cornell_box():
    """The indirect-light validation scene (sphere in a Cornell box), at R × R."""
    import yaml
    from conftest import REPO
    data = yaml.safe_load((REPO / "configs" / "validation" / "cornell.yaml").read_text())
    data["scene"]["film"] = {"width": R, "height": R}
    data["estimator"] = {"spp": 4, "boundary_spp": 256, "terms": ["indirect"], "kdtree": {"initial_samples": 65536}}
    return data


@pytest.mark.slow
def test_guided_indirect_agrees_with_unguided(tmp_path):
    """The indirect term's guides (noisy targets: one random subpath pair per evaluation) keep the
    estimate unbiased: grid and Kd-tree (sorted and not) against the unguided estimator."""
    data = cornell_box()
    m0, s0 = mean_se(direct_sums(tmp_path, data, 2 * PASSES, term="indirect", guiding="none")[0])
    assert np.abs(m0).max() > 6 * s0[np.argmax(np.abs(m0))]  # the test has power
    failures = []
    for guiding, sort in (("grid", False), ("kdtree", False), ("kdtree", True)):
        sums, guides = direct_sums(tmp_path, data, PASSES, term="indirect", guiding=guiding, edge_sort=sort)
        assert guides.get("indirect") is not None and guides["indirect"].total > 0
        m, s = mean_se(sums)
        z = (m - m0) / np.maximum(np.hypot(s, s0), 1e-12)
        print(f"indirect {guiding} sort={sort}: max |z| {np.abs(z).max():.2f}")
        if np.abs(z).max() >= 4.5:
            failures.append((guiding, sort, m.round(3), s.round(3), z.round(2)))
    assert not failures, failures


def test_check_detects_a_biased_guide(tmp_path):
    """The agreement check can fail: a guide without the uniform share (ε = 0) that is zero on
    half of the edges misses their contribution, and the z-test sees it."""
    exp = parse_experiment(copy.deepcopy(SHADOW), tmp_path / "s.yaml", cwd=tmp_path)
    exp = with_estimator(exp, sampling="light")
    scene, parameter, edges, settings = prepare(exp)
    half = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]), np.array([[0.5, 1.0, 1.0], [1.0, 1.0, 1.0]])
    corners = np.array([np.zeros(8), np.ones(8)])
    biased = KdTreeGuide(*half, corners, 0.0, GuideStats("kdtree"), (np.array([0, -1, -1]),
                         np.array([0.5, 0, 0]), np.array([1, -1, -1]), np.array([-1, 0, 1])))
    from psdr_cli.guiding.targets import Guides
    sums = []
    for guides in (Guides(), Guides(direct={"light": biased})):
        est = forward_gradient(scene, edges, parameter, 0, "direct", settings, PASSES, guides=guides)
        sums.append(mean_se(np.array([block_sums(p) for p in est.passes])))
    (m0, s0), (m1, s1) = sums
    assert np.abs(m1 - m0).max() > 4.5 * np.hypot(s0, s1)[np.argmax(np.abs(m1 - m0))], sums


def test_grad_and_guide_stats_cli(tmp_path, write_cfg, run_psdr):
    """`psdr grad` takes the guiding options; `psdr guide-stats` writes its table, JSON and plots
    (`psdr grad` a real process, the others in this process)."""
    import json
    from conftest import run_cli
    data = copy.deepcopy(SHADOW)
    data["output"] = str(tmp_path / "runs")
    data["estimator"] = {"spp": 4, "boundary_spp": 8, "terms": ["direct"], "kdtree": {"initial_samples": 4096}}
    cfg = write_cfg(data)
    r = run_cli("grad", cfg, "--guiding", "kdtree", "--sampling", "mis", "--edge-sort")
    assert r.returncode == 0, r.stderr
    summary = json.loads((tmp_path / "runs" / "shadow" / "grad" / "summary.json").read_text())
    assert summary["guiding"] == "kdtree" and summary["edge_sort"] is True
    assert "guiding" in summary["views"][0]["seconds"]
    assert r.stdout.count("guiding kdtree: direct kdtree") == 1  # said once, before the work
    r = run_psdr("grad", cfg, "--guiding", "octree")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--guiding" in r.stderr
    r = run_psdr("guide-stats", cfg, "--guides", "grid,kdtree")
    assert r.returncode == 0, r.stderr
    folder = tmp_path / "runs" / "shadow" / "guide_stats"
    stats = json.loads((folder / "guide_stats.json").read_text())
    assert set(stats["guides"]) == {"unsorted", "sorted"}
    assert stats["chains"]["sorted"]["chains"] < stats["chains"]["unsorted"]["chains"] == stats["chains"]["unsorted"]["edges"]
    for row in stats["guides"]["sorted"].values():
        assert row["leaves"] > 0 and row["memory_bytes"] > 0 and row["evaluations"] > 0 and row["normalization"] > 0
    assert (folder / "target_u1_light.png").stat().st_size > 1000
    assert (folder / "leaves_kdtree_dir_sorted.png").exists()
    assert "kdtree/light" in r.stdout


def test_compare_cli_equal_samples(tmp_path, write_cfg, run_psdr):
    """`psdr compare` runs its variants (equal samples here), writes table, JSON, grid and EXRs;
    a guided variant's error is finite and a missing section is a one-line error."""
    import json
    data = copy.deepcopy(SHADOW)
    data["output"] = str(tmp_path / "runs")
    data["estimator"] = {"spp": 4, "boundary_spp": 16, "terms": ["direct"], "kdtree": {"initial_samples": 4096}}
    data["compare"] = {"terms": ["direct"], "trials": 1, "reference_passes": 16, "variants": [
        {"label": "none", "passes": 4}, {"label": "kdtree", "guiding": "kdtree", "passes": 4}]}
    r = run_psdr("compare", write_cfg(data))
    assert r.returncode == 0, r.stderr
    folder = tmp_path / "runs" / "shadow" / "compare"
    out = json.loads((folder / "compare.json").read_text())
    assert [v["label"] for v in out["variants"]] == ["none", "kdtree"]
    assert all(np.isfinite(v["rel_mse"]) and v["passes"] == [4] for v in out["variants"])
    assert out["variants"][1]["guides"] and (folder / "grid.png").exists() and (folder / "kdtree.exr").exists()
    del data["compare"]
    r = run_psdr("compare", write_cfg(data, "no_compare.yaml"))
    assert r.returncode == 2 and "compare: missing" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_compare_passes_give_each_term_its_own_sample_count(tmp_path, monkeypatch):
    """n passes of a multi-term comparison ask every boundary term for n × boundary_spp samples
    (a shared Settings once compounded them: the second term got n² × boundary_spp)."""
    from psdr_cli.commands.compare import Comparison, Variant
    from psdr_cli.rendering import estimate
    data = copy.deepcopy(SHADOW)
    data["output"] = str(tmp_path / "runs")
    data["estimator"] = {"spp": 4, "boundary_spp": 16, "terms": ["direct", "indirect"]}
    exp = parse_experiment(data, tmp_path / "shadow.yaml", cwd=tmp_path)
    api.setup(exp)
    asked = {}

    def fake(scene, edges, parameter, view, term, settings, min_passes=1, progress=None, guides=None):
        asked[term] = (settings.boundary_spp, min_passes)
        zero = np.zeros((2, 2, 3))
        return estimate.TermEstimate(term, zero, [zero] * min_passes, [1 / min_passes] * min_passes, 0.0, None)

    monkeypatch.setattr(estimate, "forward_gradient", fake)
    Comparison(exp, ("direct", "indirect")).passes(Variant("none"), 1, 8, None)
    assert asked == {"direct": (128, 8), "indirect": (128, 8)}


def test_auto_guiding_rule():
    """auto: the direct and indirect terms get a Kd-tree from MIN_LANES lanes per pass on;
    explicit kinds apply to every term; the line names each term's choice."""
    for term in ("direct", "indirect"):
        assert auto.choose(term, auto.MIN_LANES) == "kdtree" and auto.choose(term, auto.MIN_LANES - 1) == "none"
    assert auto.choose("primary", 1 << 30) == "none"
    def resolve(guiding, terms, pixels, spp):  # the decision, for the requested terms
        return {t: k for t, k in auto.decide(guiding, pixels, spp).items() if t in terms}
    assert resolve("auto", ("interior", "direct", "indirect"), 48 * 48, 64) == \
        {"direct": "kdtree", "indirect": "kdtree"}
    assert resolve("auto", ("direct", "indirect"), 24 * 24, 64) == {"direct": "none", "indirect": "none"}
    assert resolve("grid", ("direct", "indirect"), 4, 1) == {"direct": "grid", "indirect": "grid"}
    assert resolve("auto", ("interior", "primary"), 4, 1) == {}
    line = auto.describe("auto", resolve("auto", ("direct", "indirect"), 32 * 32, 64), 32 * 32 * 64)
    assert line == "guiding auto: direct kdtree, indirect kdtree (boundary pass of 65536 lanes)"
    # in the optimisation loop auto guides nothing; an explicit kind is kept
    assert auto.in_loop("auto") == "none" and auto.in_loop("kdtree") == "kdtree" and auto.in_loop("none") == "none"
    assert auto.decide("auto", 1 << 20, 64, loop=True) == {"direct": "none", "indirect": "none"}
    assert "none in the optimisation loop" in auto.describe("auto", {"direct": "none"}, 32 * 32 * 64, loop=True)


def test_kdtree_refresh_from_a_prior_guide(variant):
    """A refresh draws one batch from the previous guide: still a normalised density that
    estimates ∫F̃ without bias, built from (1 + refine_ratio) × initial_samples evaluations."""
    first = build_kdtree(peaked, [0.2, 0.4, 0.7], limits=TreeLimits(32, 0.002), epsilon=0.05, seed=1,
                         initial_samples=4096)
    guide = build_kdtree(peaked, [0.2, 0.4, 0.7], limits=TreeLimits(32, 0.002), epsilon=0.05, seed=2,
                         initial_samples=4096, prior=first)
    assert guide.stats.evaluations == 3 * 4096 and guide.stats.leaves > 1
    rng = np.random.default_rng(4)
    p = guide.pdf_np(rng.random((200_000, 3)))
    assert abs(p.mean() - 1.0) < 4 * p.std() / np.sqrt(len(p))
    s, ps = guide.sample_np(200_000, rng)
    f = peaked(s) / ps
    truth = 0.2 * 0.1 + 0.6 * np.pi * 0.005 * 0.998
    assert abs(f.mean() - truth) < 4 * f.std() / np.sqrt(len(f))


def test_thinned_samples_keep_every_sum(variant):
    """A pass's thinned samples estimate the same sums: the kept zeros and the kept others
    stand for all of theirs (weights add up to the counts exactly), and Σ factor·f over a
    random box matches the full pass's sum within its sampling error."""
    rng = np.random.default_rng(3)
    f = np.where(rng.random(20000) < 0.3, rng.exponential(1.0, 20000), 0.0)
    keep, factor = thinned(f, 2048)
    assert len(keep) == 2048 and len(np.unique(keep)) == 2048
    nz = f[keep] > 0
    assert np.isclose(factor[nz].sum(), (f > 0).sum()) and np.isclose(factor[~nz].sum(), (f == 0).sum())
    assert nz.sum() == 2048 - 2048 // 4  # the zeros keep a quarter of the budget
    estimates = []
    for seed in range(200):  # the lanes of a pass are exchangeable: thinning after a shuffle
        order = np.random.default_rng(seed).permutation(len(f))
        k, w = thinned(f[order], 2048)
        estimates.append(np.sum(w * f[order][k]))
    estimates = np.array(estimates)
    assert abs(estimates.mean() - f.sum()) < 4 * estimates.std() / np.sqrt(len(estimates))
    small = np.r_[np.ones(10), np.zeros(5)]
    k, w = thinned(small, 2048)  # under budget: everything kept, weight 1
    assert len(k) == 15 and np.all(w == 1.0)
    # a NaN or infinite sample is kept as a zero: the saved state stays finite
    log = SampleLog({}, 64)
    u = mi.Float(np.linspace(0, 0.9, 100).astype(np.float32))
    log.record("dir", u, mi.Point2f(u, u), mi.Float(np.r_[np.nan, np.inf, np.ones(98)].astype(np.float32)),
               mi.Float(1.0))
    assert all(np.isfinite(a).all() for a in log.arrays().values())
    assert log.drawn["dir"] == 100 and np.isclose(log.samples("dir")[2].sum(), 1.0)


@pytest.mark.slow
def test_loop_fed_guides_agree_with_unguided_and_lower_the_variance(tmp_path):
    """Kd-trees fitted to the samples the direct term's own passes kept (as the optimisation loop
    fits them: a first window unguided, a second drawn from the first fit; MIS, sorted edges) estimate the same image as the unguided estimator, tile by
    tile (|z| < 4.5 over 9 tiles), with a lower variance where the signal is."""
    exp = parse_experiment(copy.deepcopy(SHADOW), tmp_path / "s.yaml", cwd=tmp_path)
    exp = with_estimator(exp, sampling="mis", guiding="kdtree", edge_sort=True)
    scene, parameter, edges, settings = prepare(exp)
    breaks = edges.breakpoints(edges.positions(mi.traverse(scene.mi_scene)))
    fitted = {}
    for window in range(2):  # the first window unguided, the second with the guides fitted to it
        log = SampleLog(fitted, 2048)
        forward_gradient(scene, edges, parameter, 0, "direct", settings, 4, guides=Guides(direct=log))
        assert set(log.kept) == {"dir", "light"} and log.drawn["light"] == R * R * 256  # 4 passes share the spp
        fitted = fitted_guides(log, breaks, settings.estimator)
    assert set(fitted) == {"dir", "light"} and all(g.total > 0 and g.stats.leaves > 8 for g in fitted.values())
    sums = []
    for guides, passes in ((Guides(), 2 * PASSES), (Guides(direct=fitted), PASSES)):
        est = forward_gradient(scene, edges, parameter, 0, "direct", settings, passes, guides=guides)
        scale = len(est.passes) * np.array(est.weights)[:, None]
        sums.append(np.array([block_sums(p) for p in est.passes]) * scale)
    (m0, s0), (m1, s1) = (mean_se(x) for x in sums)
    z = (m1 - m0) / np.maximum(np.hypot(s0, s1), 1e-12)
    assert np.abs(z).max() < 4.5, (m0, s0, m1, s1)
    signal = np.abs(m0) > 0.2 * np.abs(m0).max()
    var0 = sums[0][:, signal].var(0, ddof=1).sum()
    var1 = sums[1][:, signal].var(0, ddof=1).sum()
    assert var1 < 0.5 * var0, (var1, var0)
