"""``HumanMentor``: a person at the keyboard, gamepad or steering wheel, watching a live window.

The window (default 900x600, paced at ``fps`` = 10 Hz with ``pygame.time.Clock``; ``fps=0``
runs unpaced) shows the scene centred on the ego (highway-env's ``EnvViewer`` drawing:
road, vehicles, obstacles) with arrows for the agent's proposal (blue) and the human input
(orange), and a panel: who controls the car (AGENT / HUMAN / PHYSICS), gauges of both
actions, takeover count, speed, step and the key help line. Keys and axes:
:mod:`pe_rlhf.mentors.human_input`.

- ``decide(env, agent_action)`` handles pending events, draws a frame and returns the
  human's ``MentorDecision``; a takeover starts from ``agent_action`` (the handover of
  :mod:`~pe_rlhf.mentors.human_input`: holding only Up in a curve keeps the agent's
  steering); while paused it keeps drawing and handling events (clock ticking) until
  unpaused or quit. Call ``show_control(source)`` after it to display who
  finally drove this step (the physics/hybrid selector may pick PHYSICS); by default HUMAN
  when the person takes over, else AGENT.
- ``act(env)``: the human drives alone (demonstrations; shown as HUMAN, not counted as takeovers).
- Quit (Esc/Q, window close) sets ``quit_requested``, releases control, closes the window and
  raises nothing: from then on the agent drives (every ``decide`` is "no takeover", nothing is
  drawn) and callers may check the flag. ``screenshot(path)`` saves the window as PNG.
- ``on_disconnect`` (``mentor.kwargs.on_disconnect`` in the recipe): ``"agent"`` (default) as
  above, and an unplugged gamepad hands control back to the agent until the person drives again;
  ``"pause"``: a closed window reopens paused, an unplugged gamepad pauses, until P/Space or the
  gamepad is back (the env waits inside ``decide``). ``disconnects`` counts the times the person
  left (the trainer checkpoints after each).
Works headless under ``SDL_VIDEODRIVER=dummy``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pygame
from highway_env.envs.common.graphics import EnvViewer

from pe_rlhf.envs.action import MAX_STEERING
from pe_rlhf.mentors.base import Mentor, MentorDecision
from pe_rlhf.mentors.human_input import HELP_LINE, InputState, JoystickMapping

PANEL_HEIGHT = 150
AGENT_COLOR, HUMAN_COLOR = (40, 110, 230), (245, 140, 20)
SOURCE_COLORS = {"AGENT": AGENT_COLOR, "HUMAN": HUMAN_COLOR, "PHYSICS": (30, 160, 70)}
PANEL_BG, TEXT, DIM = (28, 30, 36), (235, 235, 235), (150, 150, 160)
ON_DISCONNECT = ("agent", "pause")


class HumanMentor(Mentor):
    """A real person as the mentor, through a pygame window (see the module docstring)."""

    name = "human"

    def __init__(self, fps: float = 10.0, size: tuple[int, int] = (900, 600),
                 mapping: JoystickMapping | None = None, input_state: InputState | None = None,
                 title: str = "PE-RLHF mentor", scaling: float = 6.0, on_disconnect: str = "agent"):
        if on_disconnect not in ON_DISCONNECT:
            raise ValueError(f"on_disconnect={on_disconnect!r} is invalid: allowed: {list(ON_DISCONNECT)}")
        self.scaling = float(scaling)  # [px/m] at 900 px width (the view spans ~150 m)
        self.fps, self.size, self.title = float(fps), (int(size[0]), int(size[1])), title
        self.input = input_state or InputState(mapping)
        self.input.pause_on_disconnect = on_disconnect == "pause"
        self.clock = pygame.time.Clock()
        self.screen: pygame.Surface | None = None
        self._viewer: EnvViewer | None = None
        self._scene: pygame.Surface | None = None
        self._fonts: dict[int, pygame.font.Font] = {}
        self.takeover_count = 0  # takeover spans started (rising edges)
        self.takeover_steps = 0
        self.steps = 0
        self.control = "AGENT"
        self.agent_action = np.zeros(2, dtype=np.float32)
        self.human_action = np.zeros(2, dtype=np.float32)
        self._taking_over = False
        self._env = None
        self._speed, self._seed, self._show_agent = 0.0, None, True

    # -- mentor interface --------------------------------------------------------------
    @property
    def quit_requested(self) -> bool:
        return self.input.quit_requested

    @property
    def paused(self) -> bool:
        return self.input.paused

    @property
    def disconnects(self) -> int:
        """Times the person left: quit key, window closed, gamepad in use unplugged."""
        return self.input.disconnects

    def reset(self, env) -> None:
        self.input.reset()
        self.steps, self._taking_over, self.control = 0, False, "AGENT"
        self.agent_action = np.zeros(2, dtype=np.float32)
        self.human_action = np.zeros(2, dtype=np.float32)
        if self.input.quit_requested:
            return
        self._handle_events()
        self._draw(env)

    def decide(self, env, agent_action: np.ndarray) -> MentorDecision:
        self.agent_action = np.clip(np.asarray(agent_action, dtype=np.float32).reshape(2), -1, 1)
        takeover, action = self._step(env, agent=True)
        return MentorDecision(takeover, action)

    def act(self, env) -> np.ndarray:
        _, action = self._step(env, agent=False)
        return action

    def show_control(self, source: str) -> None:
        """Display who drives this step ("AGENT", "HUMAN" or "PHYSICS"); call after ``decide``."""
        source = source.upper()
        if source not in SOURCE_COLORS:
            raise ValueError(f"source must be one of {sorted(SOURCE_COLORS)}, got {source!r}")
        self.control = source
        if self._scene is not None:
            self._compose()

    def state_dict(self) -> dict[str, Any]:
        return {"takeover_count": self.takeover_count, "takeover_steps": self.takeover_steps}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.takeover_count = int(state.get("takeover_count", 0))
        self.takeover_steps = int(state.get("takeover_steps", 0))

    def screenshot(self, path) -> Path:
        """Save the current window as PNG; returns the path."""
        if self.screen is None:
            raise RuntimeError("no window yet: call reset() or decide() first")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        pygame.image.save(self.screen, str(path))
        return path

    def close(self) -> None:
        """Close the window (the mentor reopens one if used again)."""
        if self.screen is not None:
            pygame.display.quit()
        self.screen, self._viewer, self._scene = None, None, None

    # -- one step ----------------------------------------------------------------------
    def _step(self, env, agent: bool) -> tuple[bool, np.ndarray]:
        if not self.input.quit_requested:
            self._handle_events()
            while self.input.paused and not self.input.quit_requested:
                self._draw(env)
                self._tick()
                self._handle_events()
        if self.input.quit_requested:  # the person left: the agent drives, the window is gone
            self.close()
            self.steps += 1
            self._taking_over, self.control = False, "AGENT"
            self.human_action = np.zeros(2, dtype=np.float32)
            return False, self.human_action
        takeover, action, _, _ = self.input.poll(self.agent_action if agent else None)
        if agent:  # takeovers of the agent are counted; driving alone (act) is not one
            self.takeover_count += int(takeover and not self._taking_over)
            self.takeover_steps += int(takeover)
            self._taking_over = takeover
        else:
            takeover = True  # driving alone: the human always controls
        self.human_action = action
        self.control = "HUMAN" if takeover else "AGENT"
        self.steps += 1
        self._draw(env, show_agent=agent)
        self._tick()
        return takeover, action

    def _handle_events(self) -> None:
        self._ensure_window()
        self.input.pump()
        if self.input.window_closed:  # closed by the person: gone, or reopened (paused) by the next draw
            self.close()

    def _tick(self) -> None:
        if self.fps > 0:
            self.clock.tick(self.fps)

    # -- drawing -----------------------------------------------------------------------
    def _ensure_window(self) -> None:
        if self.screen is not None and pygame.display.get_surface() is self.screen:
            return
        pygame.display.init()
        pygame.font.init()
        self.screen = pygame.display.set_mode(self.size)
        pygame.display.set_caption(self.title)
        self.input.open_joysticks()
        self.input.window_closed = False
        self._viewer, self._fonts = None, {}

    def _font(self, px: int) -> pygame.font.Font:
        if px not in self._fonts:
            self._fonts[px] = pygame.font.Font(None, px)
        return self._fonts[px]

    def _draw(self, env, show_agent: bool = True) -> None:
        self._ensure_window()
        env = getattr(env, "unwrapped", env)
        if self._viewer is None or self._env is not env:
            w, h = self.size[0], self.size[1] - PANEL_HEIGHT
            config = {**env.config, "offscreen_rendering": True, "screen_width": w, "screen_height": h,
                      "scaling": self.scaling * w / 900, "centering_position": [0.3, 0.5]}
            self._viewer, self._env = EnvViewer(env, config), env
            self._viewer.enabled = True  # highway-env disables drawing under the dummy driver
            pygame.display.set_caption(self.title)
        self._viewer.display()  # offscreen: draws onto viewer.sim_surface only
        self._scene = self._viewer.sim_surface
        self._show_agent = show_agent
        self._speed = float(env.vehicle.speed * 3.6) if env.vehicle is not None else 0.0
        self._seed = getattr(env, "scene_seed", None)
        self._compose()

    def _arrow(self, surface, action: np.ndarray, color) -> None:
        """An arrow from the ego: direction = heading + steering angle, length ~ throttle."""
        ego = self._env.vehicle if self._env is not None else None
        if ego is None:
            return
        sim = self._viewer.sim_surface
        angle = ego.heading + float(action[0]) * MAX_STEERING
        length = 6.0 + 10.0 * max(float(action[1]), 0.0)
        start = np.array(sim.pos2pix(*ego.position), dtype=float)
        d = np.array([math.cos(angle), math.sin(angle)])
        end = start + sim.pix(length) * d
        pygame.draw.line(surface, color, start, end, 4)
        n = np.array([-d[1], d[0]])
        pygame.draw.polygon(surface, color, [end + 12 * d, end + 7 * n, end - 7 * n])
        if action[1] < 0:  # braking: a bar across the arrow's root
            root = start + sim.pix(4.0) * d
            pygame.draw.line(surface, color, root + 12 * n, root - 12 * n, 5)

    def _text(self, s: str, pos, px: int = 22, color=TEXT, center: bool = False) -> None:
        img = self._font(px).render(s, True, color)
        rect = img.get_rect(center=pos) if center else img.get_rect(topleft=pos)
        self.screen.blit(img, rect)

    def _gauge(self, x: int, y: int, label: str, action: np.ndarray, color) -> None:
        """Label, a steering bar (centre = straight) and a throttle bar (right = gas, left = brake)."""
        self._text(label, (x, y), 22, color)
        for row, (name, v) in enumerate((("steer", action[0]), ("throttle", action[1]))):
            top, w = y + 24 + row * 26, 200
            self._text(f"{name} {v:+.2f}", (x, top + 2), 19, DIM)
            bx = x + 100
            pygame.draw.rect(self.screen, (60, 62, 70), (bx, top, w, 16))
            mid = bx + w // 2
            end = mid + int(float(np.clip(v, -1, 1)) * w / 2)
            pygame.draw.rect(self.screen, color, (min(mid, end), top, abs(end - mid), 16))
            pygame.draw.line(self.screen, TEXT, (mid, top - 2), (mid, top + 17), 1)

    def overlay_lines(self) -> list[str]:
        """The panel's text as drawn: control, takeover count, speed, help line."""
        return [self.control, f"takeovers: {self.takeover_count}",
                f"speed: {self._speed:5.1f} km/h", HELP_LINE]

    def _compose(self) -> None:
        """Blit the cached scene and draw the arrows and the panel onto the window."""
        W, H = self.size
        scene_h = H - PANEL_HEIGHT
        self.screen.blit(self._scene, (0, 0))
        ego = self._env.vehicle if self._env is not None else None
        if ego is not None:  # a ring in the controller's colour marks the ego car
            centre = self._viewer.sim_surface.pos2pix(*ego.position)
            pygame.draw.circle(self.screen, SOURCE_COLORS[self.control], centre,
                               self._viewer.sim_surface.pix(4.0), 3)
        if self._show_agent:
            self._arrow(self.screen, self.agent_action, AGENT_COLOR)
        if self.control == "HUMAN" or not self._show_agent:
            self._arrow(self.screen, self.human_action, HUMAN_COLOR)
        seed = "" if self._seed is None else f"scene {self._seed}   "
        self._text(f"{seed}step {self.steps}", (10, 8), 22, (20, 20, 20))
        if self.input.paused:
            veil = pygame.Surface((W, scene_h), pygame.SRCALPHA)
            veil.fill((0, 0, 0, 110))
            self.screen.blit(veil, (0, 0))
            reason = f" ({self.input.pause_reason})" if self.input.pause_reason else ""
            self._text(f"PAUSED{reason} - press P or Space", (W // 2, scene_h // 2), 48, (255, 255, 255),
                       center=True)
        pygame.draw.rect(self.screen, PANEL_BG, (0, scene_h, W, PANEL_HEIGHT))
        control, takeovers, speed = self.overlay_lines()[:3]
        pygame.draw.rect(self.screen, SOURCE_COLORS[control], (12, scene_h + 12, 170, 52), border_radius=8)
        self._text(control, (97, scene_h + 38), 40, (255, 255, 255), center=True)
        self._text(takeovers, (12, scene_h + 74), 24)
        self._text(speed, (12, scene_h + 98), 24)
        if self._show_agent:
            self._gauge(int(W * 0.23), scene_h + 10, "agent proposes", self.agent_action, AGENT_COLOR)
        self._gauge(int(W * 0.6), scene_h + 10, "human input", self.human_action, HUMAN_COLOR)
        self._text(self.overlay_lines()[3], (12, H - 24), 19, DIM)
        pygame.display.flip()
