"""The time left in a training run: the ``eta_s`` of the trainer's progress events.

A run's time is not spread evenly over its iterations. A camera-tracking round (``camera_tracking``) renders
every training frame ``len(levels) x steps`` times while the iteration count stands still, and a topology
evolution runs between two iterations. On the dashcam sample at ``fast`` (the README's demo on an AMD EPYC VM
without AVX-512, before that preset skipped the rounds on clips whose cameras SfM registered) the two rounds took
124 and 130 s of 657 s of training, against 0.27 s for an iteration.
The elapsed time per elapsed iteration, times the iterations left, read 27 min just after the first round with
under 9 min to go, and then fell for the rest of the run. So the clock keeps the three costs apart and adds up
what is still ahead:

    eta = step x iterations left + tracking step x tracking steps left + evolution x evolutions left

- **step**: the mean time of the last ``window`` iterations without an evolution (the map grows, so the recent
  ones tell the cost of the next);
- **tracking step**: one Adam step of a round, which renders every training frame once: the mean over the steps
  of the latest round timed. Before any has been timed it is guessed as ``render_share`` of an iteration per
  frame: an iteration renders one frame and also steps every optimiser and the densifier, and a frame's render
  in a round took 0.74 of an iteration on the demo (6.2 s a step over 31 frames, against 0.27 s) and 0.77 on
  the synthetic suite at ``balanced`` (6.1 s over 19 frames, against about 0.41 s);
- **evolution**: the mean of the timed ones, 0 until one is.
"""

from __future__ import annotations

from collections import deque


class RunClock:
    """Times of a run's iterations, tracking steps and evolutions, and the estimate of the time left."""

    def __init__(self, window: int = 100, render_share: float = 0.75):
        self.render_share = render_share
        self._steps: deque[float] = deque(maxlen=window)  # seconds of recent plain iterations
        self._round: list[float] = []  # seconds of each step of the latest tracking round
        self._evolutions: list[float] = []

    def step(self, seconds: float) -> None:
        self._steps.append(seconds)

    def evolution(self, seconds: float) -> None:
        self._evolutions.append(seconds)

    def tracking_step(self, seconds: float, first: bool) -> None:
        """One tracking step; ``first``: the first step of a round (the latest round's mean starts afresh)."""
        if first:
            self._round = []
        self._round.append(seconds)

    def seconds_per_step(self) -> float:
        return sum(self._steps) / len(self._steps) if self._steps else 0.0

    def seconds_per_tracking_step(self, frames: int) -> float:
        if self._round:
            return sum(self._round) / len(self._round)
        return self.render_share * frames * self.seconds_per_step()

    def eta(self, iterations_left: int, tracking_steps_left: int = 0, evolutions_left: int = 0,
            frames: int = 1) -> float:
        """Seconds left: ``iterations_left`` iterations, ``tracking_steps_left`` tracking steps over ``frames``
        training frames and ``evolutions_left`` evolutions, each at its current cost (module docstring)."""
        evolution = sum(self._evolutions) / len(self._evolutions) if self._evolutions else 0.0
        return (max(iterations_left, 0) * self.seconds_per_step()
                + max(tracking_steps_left, 0) * self.seconds_per_tracking_step(frames)
                + max(evolutions_left, 0) * evolution)
