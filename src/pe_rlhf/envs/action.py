"""The normalised driving action ``[steering, throttle]`` and its vehicle controls.

Every policy in the package (agent, physics, mentors) speaks this action:

- ``steering`` in [-1, 1] -> front-wheel angle ``steering * MAX_STEERING`` [rad];
  positive turns towards the ego's +lateral side (highway-env's lane-index-increasing
  side, "right" on screen).
- ``throttle`` in [-1, 1] -> longitudinal acceleration: ``throttle * MAX_ACCELERATION``
  when positive, ``throttle * MAX_BRAKING`` when negative. Braking stops the car;
  it never reverses (the env clamps speed at 0).
"""

from __future__ import annotations

import numpy as np

MAX_STEERING = 0.5  # [rad] front-wheel angle at |steering| = 1
MAX_ACCELERATION = 3.0  # [m/s^2] at throttle = +1
MAX_BRAKING = 6.0  # [m/s^2] at throttle = -1


def action_to_controls(action) -> tuple[float, float]:
    """Map a normalised ``[steering, throttle]`` to ``(steering_angle [rad], acceleration [m/s^2])``.

    Values outside [-1, 1] are clipped; NaN raises ``ValueError`` (a NaN action must
    never reach the simulator silently).
    """
    a = np.asarray(action, dtype=np.float64).reshape(-1)
    if a.shape != (2,):
        raise ValueError(f"action must have 2 entries [steering, throttle], got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"action must be finite, got {a.tolist()}")
    steering, throttle = np.clip(a, -1.0, 1.0)
    accel = throttle * (MAX_ACCELERATION if throttle >= 0 else MAX_BRAKING)
    return float(steering * MAX_STEERING), float(accel)


def controls_to_action(steering_angle: float, acceleration: float) -> np.ndarray:
    """Inverse of :func:`action_to_controls`, clipped to [-1, 1]; returns float32 ``(2,)``."""
    steering = steering_angle / MAX_STEERING
    throttle = acceleration / (MAX_ACCELERATION if acceleration >= 0 else MAX_BRAKING)
    return np.clip(np.array([steering, throttle], dtype=np.float32), -1.0, 1.0)
