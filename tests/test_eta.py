"""The run clock behind the progress events' ``eta_s``: iterations, tracking steps and evolutions kept apart."""

from __future__ import annotations

import pytest

from agg.train.eta import RunClock
from service.demo import describe


def test_each_cost_is_counted_once_at_its_own_rate():
    clock = RunClock(window=100)
    for _ in range(100):
        clock.step(0.1)
    for i in range(4):  # a tracking round of 4 steps; the iterations' rate does not take it up
        clock.tracking_step(2.0, first=i == 0)
    clock.evolution(5.0)
    assert clock.seconds_per_step() == pytest.approx(0.1)
    # 50 iterations, 8 tracking steps (two more rounds) and one evolution left
    assert clock.eta(50, 8, 1, frames=30) == pytest.approx(50 * 0.1 + 8 * 2.0 + 5.0)
    assert clock.eta(0) == 0.0


def test_recent_iterations_set_the_rate_and_the_latest_round_the_tracking_step():
    clock = RunClock(window=10)
    for _ in range(20):
        clock.step(1.0)
    for _ in range(10):  # the map grew: only the last 10 iterations count
        clock.step(0.5)
    assert clock.seconds_per_step() == pytest.approx(0.5)
    clock.tracking_step(4.0, first=True)
    clock.tracking_step(4.0, first=False)
    clock.tracking_step(3.0, first=True)  # a new round starts its own mean
    assert clock.seconds_per_tracking_step(frames=30) == pytest.approx(3.0)


def test_an_untimed_round_is_guessed_from_the_iterations():
    clock = RunClock(render_share=0.5)
    assert clock.eta(100, 40, 4, frames=30) == 0.0  # nothing timed yet
    clock.step(0.2)
    # each tracking step renders the 30 training frames at half an iteration each; evolutions count 0 untimed
    assert clock.eta(100, 40, 4, frames=30) == pytest.approx(100 * 0.2 + 40 * 0.5 * 30 * 0.2)


def test_the_demo_bar_shows_a_tracking_round():
    event = {"stage": "train", "iteration": 125, "total": 1500, "phase": "warmup", "loss": None, "psnr": None,
             "n_gaussians": 40_000, "eta_s": 530.0, "tracking": {"step": 12, "steps": 40}}
    desc, postfix = describe(event)
    assert desc == "training (warmup)"
    assert postfix == "it 125/1500, tracking cameras 12/40, 40,000 G, ETA 8:50"
