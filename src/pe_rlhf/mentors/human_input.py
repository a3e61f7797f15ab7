"""Keyboard, gamepad and steering-wheel input turned into ``[steering, throttle]`` + a takeover flag.

:class:`InputState` consumes a pygame event stream (``handle(event)``; real or posted with
``pygame.event.post``) and keeps the held keys, axes and buttons itself, so synthetic events
drive it exactly like a person does. ``poll(agent_action)`` is called once per env step and returns
``InputPoll(takeover, action, paused, quit)``.

Keyboard (any driving key held = takeover; releasing all of them hands control back):

- Left/A, Right/D: steering ramps by ``steer_rate`` (0.1) per poll towards -1/+1; reversing the
  direction the person last steered restarts from 0; released, it returns towards 0 by
  ``steer_return`` (0.2) per poll.
- Up/W: throttle +1. Down/S: throttle -1 (brake; wins over Up when both are held). Neither: 0.
- P/Space: pause toggle. Esc/Q or closing the window: quit. Losing window focus releases keys.

Handover (``poll(agent_action)`` on the poll where a takeover starts; ``HumanMentor.decide`` passes the
agent's proposed action): the person's input starts from the agent's ``[steering, throttle]``, not from
their own last values (0 after a reset). An axis the person has not touched since the handover (no
Left/Right, no Up/Down, a stick or pedal inside its deadzone) keeps the agent's value, so holding only
Up in a curve keeps the agent's steering; Left/Right ramp from the agent's steering by ``steer_rate``
(no restart from 0 when they turn back from it), so the first human steering is within one
``steer_rate`` of the agent's; Up/Down and a moved stick or pedal command their own value at once
(braking must not wait for a ramp). Once touched, an axis behaves as above. ``poll()`` without an agent
action (driving alone: ``HumanMentor.act``) starts from the person's own values.

The person leaving (``disconnects`` counts each time): Esc/Q always quits (``quit_requested``: the
agent drives from then on), and so, by default, does closing the window; unplugging the gamepad in
use hands control back to the agent until the person drives again (keys or another device). With
``pause_on_disconnect`` a closed window or an unplugged gamepad pauses instead (``pause_reason`` says
why) until the person presses P/Space or plugs a gamepad back in.

Joystick (any device pygame sees; :class:`JoystickMapping`, hot-plugged via
``JOYDEVICEADDED``/``JOYDEVICEREMOVED``; an unplugged device releases control). Each axis goes
through the rescaled deadzone ``dz(v) = sign(v) * max(0, |v| - d) / (1 - d)`` (``d`` = 0.1:
0.6 -> 5/9 ~= 0.556, 1 -> 1, continuous at the deadzone edge):

- ``steering = dz(axis[steering_axis])`` (default axis 0, left stick / wheel).
- ``throttle_mode="stick"`` (default): ``throttle = dz(-axis[throttle_axis])`` (axis 1, stick
  pushed up = negative value = accelerate, pulled back = brake).
- ``throttle_mode="pedals"`` (triggers/pedals resting at -1, e.g. Xbox triggers axes 5/4 in
  SDL): ``throttle = dz((gas+1)/2) - dz((brake+1)/2)``; ``invert_pedals`` for pedals resting at +1.

Takeover from a joystick: any mapped axis beyond the deadzone, or any button held (paddles;
``takeover_buttons`` restricts which). ``pause_button`` (default None) toggles pause.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pygame

LEFT_KEYS = frozenset({pygame.K_LEFT, pygame.K_a})
RIGHT_KEYS = frozenset({pygame.K_RIGHT, pygame.K_d})
UP_KEYS = frozenset({pygame.K_UP, pygame.K_w})
DOWN_KEYS = frozenset({pygame.K_DOWN, pygame.K_s})
DRIVING_KEYS = LEFT_KEYS | RIGHT_KEYS | UP_KEYS | DOWN_KEYS
PAUSE_KEYS = frozenset({pygame.K_p, pygame.K_SPACE})
QUIT_KEYS = frozenset({pygame.K_ESCAPE, pygame.K_q})
HELP_LINE = ("Arrows/WASD: drive (hold = take over)   P/Space: pause   Esc/Q: quit   "
             "gamepad: stick/pedals, any button = take over")


class InputPoll(NamedTuple):
    """One step of input: unpacks as ``takeover, action, paused, quit``."""

    takeover: bool
    action: np.ndarray  # float32 (2,) [steering, throttle]
    paused: bool
    quit: bool


@dataclass(frozen=True)
class JoystickMapping:
    """How a gamepad or steering wheel maps to ``[steering, throttle]`` (see the module docstring)."""

    steering_axis: int = 0
    throttle_mode: str = "stick"  # "stick" or "pedals"
    throttle_axis: int = 1  # stick mode: inverted (up = accelerate, down = brake)
    gas_axis: int = 5  # pedals mode: right trigger / gas pedal
    brake_axis: int = 4  # pedals mode: left trigger / brake pedal
    invert_pedals: bool = False  # pedals resting at +1 instead of -1
    deadzone: float = 0.1
    takeover_buttons: tuple[int, ...] | None = None  # None: any button takes over
    pause_button: int | None = None

    def __post_init__(self) -> None:
        if self.throttle_mode not in ("stick", "pedals"):
            raise ValueError(f"throttle_mode must be 'stick' or 'pedals', got {self.throttle_mode!r}")
        if not 0.0 <= self.deadzone < 1.0:
            raise ValueError(f"deadzone must be in [0, 1), got {self.deadzone}")

    def dz(self, v: float) -> float:
        """Rescaled deadzone: 0 inside ``deadzone``, then linear up to 1 (continuous)."""
        m = max(0.0, abs(v) - self.deadzone) / (1.0 - self.deadzone)
        return float(np.sign(v) * min(m, 1.0))

    def action(self, axes: dict[int, float]) -> tuple[float, float]:
        """``(steering, throttle)`` from the latest axis values (missing axes are at rest)."""
        steering = self.dz(axes.get(self.steering_axis, 0.0))
        if self.throttle_mode == "stick":
            throttle = self.dz(-axes.get(self.throttle_axis, 0.0))
        else:
            rest = 1.0 if self.invert_pedals else -1.0

            def pedal(axis: int) -> float:
                v = axes.get(axis, rest)
                return self.dz((1.0 - v) / 2.0 if self.invert_pedals else (v + 1.0) / 2.0)

            throttle = pedal(self.gas_axis) - pedal(self.brake_axis)
        return steering, float(np.clip(throttle, -1.0, 1.0))


class InputState:
    """Keyboard + joystick state from pygame events; ``poll()`` once per env step."""

    def __init__(self, mapping: JoystickMapping | None = None, steer_rate: float = 0.1,
                 steer_return: float = 0.2, keyboard: bool = True, joystick: bool = True,
                 pause_on_disconnect: bool = False):
        self.mapping = mapping or JoystickMapping()
        self.steer_rate, self.steer_return = float(steer_rate), float(steer_return)
        self.use_keyboard, self.use_joystick = keyboard, joystick
        self.held: set[int] = set()
        self.key_steering = 0.0
        # The agent's steering / throttle at the last handover, per axis the person has not touched since
        # (None: the person's own value); see the module docstring.
        self.agent_steering: float | None = None
        self.agent_throttle: float | None = None
        self._taking_over = False  # the previous poll's takeover (a handover is its rising edge)
        self._key_direction = 0.0  # the last steering key's direction (-1 left, +1 right; 0: none since a handover)
        self.axes: dict[int, dict[int, float]] = {}  # instance_id -> axis -> raw value
        self.buttons: dict[int, set[int]] = {}  # instance_id -> held buttons
        self.devices: dict[int, object] = {}  # instance_id -> opened pygame Joystick
        self.paused = False
        self.quit_requested = False
        self.pause_on_disconnect = bool(pause_on_disconnect)
        self.pause_reason: str | None = None  # "window closed" / "gamepad unplugged" while such a pause lasts
        self.window_closed = False  # the window was closed: whoever draws must close and reopen it
        self.disconnects = 0  # times the person left: quit key, window closed, gamepad in use unplugged

    # -- events ----------------------------------------------------------------------
    def open_joysticks(self) -> None:
        """Open every joystick already connected (hot-plugged ones arrive as events)."""
        if not self.use_joystick:
            return
        if not pygame.joystick.get_init():
            pygame.joystick.init()
        for i in range(pygame.joystick.get_count()):
            self._add_device(i)

    def _add_device(self, device_index: int) -> None:
        try:
            js = pygame.joystick.Joystick(device_index)
            js.init()
        except pygame.error:  # a synthetic or already-gone device: its events still count
            return
        self.devices[js.get_instance_id()] = js

    def _release_device(self, instance_id: int) -> None:
        self.devices.pop(instance_id, None)
        self.axes.pop(instance_id, None)
        self.buttons.pop(instance_id, None)

    def handle(self, event) -> None:
        """Update the state from one pygame event (others are ignored)."""
        t = event.type
        if t in (pygame.QUIT, pygame.WINDOWCLOSE):
            if not self.window_closed:  # SDL sends both for one click
                self.window_closed = True
                self._disconnect("window closed")
        elif t == pygame.WINDOWFOCUSLOST:
            self.held.clear()  # a key released while unfocused would otherwise stay held
        elif t == pygame.KEYDOWN and self.use_keyboard:
            key = event.key
            if key in QUIT_KEYS:
                self.disconnects += int(not self.quit_requested)
                self.quit_requested = True
            elif key in PAUSE_KEYS:
                self.paused, self.pause_reason = not self.paused, None
            elif key in DRIVING_KEYS:
                self.held.add(key)
        elif t == pygame.KEYUP and self.use_keyboard:
            self.held.discard(event.key)
        elif not self.use_joystick:
            return
        elif t == pygame.JOYAXISMOTION:
            self.axes.setdefault(event.instance_id, {})[event.axis] = float(event.value)
        elif t == pygame.JOYBUTTONDOWN:
            if event.button == self.mapping.pause_button:
                self.paused, self.pause_reason = not self.paused, None
            else:
                self.buttons.setdefault(event.instance_id, set()).add(event.button)
        elif t == pygame.JOYBUTTONUP:
            self.buttons.get(event.instance_id, set()).discard(event.button)
        elif t == pygame.JOYDEVICEADDED:
            self._add_device(event.device_index)
            if self.pause_reason == "gamepad unplugged":  # plugged back in: drive on
                self.paused, self.pause_reason = False, None
        elif t == pygame.JOYDEVICEREMOVED:
            in_use = event.instance_id in self.axes or event.instance_id in self.buttons
            self._release_device(event.instance_id)
            if in_use and not (self.axes or self.buttons):
                self._disconnect("gamepad unplugged")

    def _disconnect(self, reason: str) -> None:
        """The person left: pause (``pause_on_disconnect``), else a closed window quits (the agent drives
        from then on) and an unplugged gamepad has already handed control back (keys still work)."""
        self.disconnects += 1
        if self.pause_on_disconnect and not self.quit_requested:
            self.paused, self.pause_reason = True, reason
        elif reason == "window closed":
            self.quit_requested = True

    def pump(self) -> None:
        """Handle every pending pygame event."""
        for event in pygame.event.get():
            self.handle(event)

    # -- state -----------------------------------------------------------------------
    def keyboard_driving(self) -> bool:
        return bool(self.held & DRIVING_KEYS)

    def _joystick(self) -> tuple[bool, float, float]:
        """(takeover, steering, throttle) of the most active device."""
        best = (False, 0.0, 0.0)
        for iid in set(self.axes) | set(self.buttons):
            steering, throttle = self.mapping.action(self.axes.get(iid, {}))
            pressed = self.buttons.get(iid, set())
            if self.mapping.takeover_buttons is not None:
                pressed = pressed & set(self.mapping.takeover_buttons)
            active = bool(pressed) or steering != 0.0 or throttle != 0.0
            if active and (not best[0] or abs(steering) + abs(throttle) > abs(best[1]) + abs(best[2])):
                best = (True, steering, throttle)
        return best

    def _advance_keys(self) -> tuple[float, float]:
        left, right = bool(self.held & LEFT_KEYS), bool(self.held & RIGHT_KEYS)
        direction = (1.0 if right else 0.0) - (1.0 if left else 0.0)
        s = self.key_steering
        if direction != 0.0:
            if s * direction < 0.0 and direction == -self._key_direction:
                s = 0.0  # the person's counter-steer starts from straight, not from the opposite lock
            s = float(np.clip(round(s + direction * self.steer_rate, 9), -1.0, 1.0))
            self.agent_steering, self._key_direction = None, direction
        elif self.agent_steering is not None:
            s = self.agent_steering  # untouched since the handover: the agent's steering stays
        else:
            s = float(np.sign(s) * max(0.0, round(abs(s) - self.steer_return, 9)))
        self.key_steering = s
        if self.held & (UP_KEYS | DOWN_KEYS):
            self.agent_throttle = None
        if self.held & DOWN_KEYS:
            return s, -1.0
        if self.held & UP_KEYS:
            return s, 1.0
        return s, 0.0 if self.agent_throttle is None else self.agent_throttle

    def _hand_over(self, agent_action) -> None:
        """A takeover starts: the person's input starts from the agent's ``[steering, throttle]``."""
        a = np.asarray(agent_action, dtype=np.float64).reshape(2)
        if not np.isfinite(a).all():  # nothing sensible to start from: the person's own values
            return
        self.agent_steering, self.agent_throttle = (float(v) for v in np.clip(a, -1.0, 1.0))
        self.key_steering, self._key_direction = self.agent_steering, 0.0

    def _joystick_action(self, steering: float, throttle: float) -> tuple[float, float]:
        """The device's action, with the axes untouched since the handover (at rest) kept at the agent's."""
        if steering != 0.0:
            self.agent_steering = None
        if throttle != 0.0:
            self.agent_throttle = None
        return (steering if self.agent_steering is None else self.agent_steering,
                throttle if self.agent_throttle is None else self.agent_throttle)

    def poll(self, agent_action=None) -> InputPoll:
        """Advance the keyboard ramps one step and return this step's input. ``agent_action``
        (``[steering, throttle]``, what the agent proposes now): a takeover starting at this poll is a
        handover from it (see the module docstring); None: input starts from the person's own values."""
        keyboard = self.keyboard_driving()
        j_take, j_steer, j_throttle = self._joystick()
        takeover = keyboard or j_take
        if not takeover:
            self.agent_steering = self.agent_throttle = None
        elif not self._taking_over and agent_action is not None:
            self._hand_over(agent_action)
        self._taking_over = takeover
        k_steer, k_throttle = self._advance_keys()
        if keyboard:
            action = (k_steer, k_throttle)
        elif j_take:
            action = self._joystick_action(j_steer, j_throttle)
        else:
            action = (k_steer, 0.0)
        return InputPoll(takeover, np.asarray(action, dtype=np.float32), self.paused, self.quit_requested)

    def reset(self) -> None:
        """Forget ramps, the handover and the pause (held keys and devices stay: a person may keep
        holding, and their first poll of the episode is a handover)."""
        self.key_steering, self._key_direction = 0.0, 0.0
        self.agent_steering = self.agent_throttle = None
        self._taking_over = False
        if self.pause_reason is None:  # a pause for a disconnect lasts until the person is back
            self.paused = False
