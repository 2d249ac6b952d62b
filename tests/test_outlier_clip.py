"""optimize.outlier_clip: one gradient spike (a heavy-tailed sample spread over the shape by the
large-steps preconditioner) must not push or stall the uniform Adam of the loop (the interior term's surface-to-surface segments at max_depth ≥ 3 draw such samples:
docs/benchmarks/unknown_light.md)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from psdr_cli.errors import ConfigError
from psdr_cli.experiment.load import parse_experiment
from psdr_cli.support import backend
from conftest import experiment as base_experiment
from psdr_cli.optimisation.outlier_clip import AUTO_FACTOR, WARMUP, clip_factor, clip_outliers


def noisy_steps(clip: float | None, outlier: float = 30.0, steps: int = 80, at: int = 30, seed: int = 0):
    """Positions of a uniform Adam (lr 0.01) fed zero-mean unit noise on 200 entries plus, on step
    ``at``, a coherent spike of ``outlier`` on every entry: (x after each step, steps clipped)."""
    backend.select_variant("llvm_ad_rgb")
    rng = np.random.default_rng(seed)
    opt = mi.ad.Adam(lr=0.01, uniform=True)
    opt["x"] = mi.Float(np.zeros(200, np.float32))
    xs, clipped = [], 0
    for k in range(steps):
        g = rng.standard_normal(200).astype(np.float32)
        if k == at:
            g += outlier
        dr.enable_grad(opt["x"])
        dr.set_grad(opt["x"], mi.Float(g))
        clipped += clip_outliers(opt, clip)
        opt.step()
        xs.append(np.asarray(opt["x"]).copy())
    return np.array(xs), clipped


def push_and_stall(xs):
    """(mean displacement of the entries over the 50 steps after the spike, their mean step after
    it over their mean step before it)."""
    push = float((xs[-1] - xs[29]).mean())
    return push, np.abs(np.diff(xs[40:], axis=0)).mean() / np.abs(np.diff(xs[10:30], axis=0)).mean()


def test_a_spike_pushes_and_stalls_an_unclipped_uniform_adam():
    """The failure the clip is for: one step whose gradient is 30σ on every entry moves the
    entries ≈ 6 learning rates together and halves every later step (the spike stays in the
    second moment for thousands of steps)."""
    push, stall = push_and_stall(noisy_steps(None)[0])
    assert push < -0.045 and stall < 0.6


def test_a_clipped_spike_pushes_less_and_does_not_stall():
    xs, clipped = noisy_steps(AUTO_FACTOR)
    push, stall = push_and_stall(xs)
    assert clipped == 1
    assert abs(push) < 0.5 * abs(push_and_stall(noisy_steps(None)[0])[0])
    assert stall > 0.9


def test_no_clip_before_the_warmup_and_none_of_plain_noise():
    _, early = noisy_steps(AUTO_FACTOR, at=WARMUP - 2, steps=WARMUP - 1)
    assert early == 0
    _, plain = noisy_steps(AUTO_FACTOR, outlier=0.0)
    assert plain == 0  # a norm of unit noise never reaches 3 times its running mean


def test_auto_clips_from_the_first_surface_to_surface_segment():
    assert clip_factor("auto", 2) is None and clip_factor("auto", 3) == AUTO_FACTOR
    assert clip_factor("off", 6) is None and clip_factor(5, 2) == 5.0


def experiment(clip):
    d = base_experiment()
    d["optimize"] = {"object": d["scene"]["objects"][0]["name"], "outlier_clip": clip}
    return d


@pytest.mark.parametrize("clip, expected", [("auto", "auto"), ("off", "off"), (4, 4.0)])
def test_outlier_clip_key(tmp_path, clip, expected):
    assert parse_experiment(experiment(clip), tmp_path / "e.yaml", cwd=tmp_path).optimize.outlier_clip == expected


@pytest.mark.parametrize("clip", ["sometimes", 0.5, True])
def test_bad_outlier_clip_is_one_line(tmp_path, clip):
    with pytest.raises(ConfigError, match=r"optimize\.outlier_clip: expected"):
        parse_experiment(experiment(clip), tmp_path / "e.yaml", cwd=tmp_path)
