"""Record one driving episode of any evaluation policy as a labelled GIF (headless, Pillow only).

Each frame carries a caption band under the road: the step, the speed and who drives (``agent``,
``mentor`` or ``physics``, read from the step's ``info`` as :class:`~pe_rlhf.wrappers.InterventionWrapper`
reports it), coloured by the driver so takeovers stand out at a glance.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from pe_rlhf.envs import DrivingConfig, make_gym_env
from pe_rlhf.evaluation.policies import Policy

DEFAULT_SCALE = 0.75  # the 800x450 render becomes 600x338 (+ caption): cars and lane marks readable, ~3.5 MB a 40 s GIF
CAPTION_HEIGHT = 26  # pixels of the caption band (output size, whatever the scale)
DRIVER_COLOURS = {"agent": (60, 140, 255), "mentor": (250, 170, 40), "physics": (70, 200, 110)}


def driver_of(info: Mapping[str, Any]) -> str:
    """Who drove the step whose ``info`` this is: ``agent``; in a takeover ``mentor``, or ``physics``
    when the selector executed the physics action (``mentor_selected`` false with a ``physics_action``)."""
    if not info.get("is_intervention", info.get("intervention", False)):
        return "agent"
    if "physics_action" in info and not info.get("mentor_selected", True):
        return "physics"
    return "mentor"


def frame_caption(step: int, info: Mapping[str, Any]) -> tuple[str, str]:
    """``("step 12   54 km/h", driver)`` for the frame after ``step`` steps (``velocity`` from ``info``)."""
    speed = info.get("velocity")
    text = f"step {step:>3d}" + (f"   {float(speed):3.0f} km/h" if speed is not None else "")
    return text, driver_of(info)


def _font(size: int) -> ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)  # Pillow's bundled font, scalable with FreeType
    except TypeError:  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def _scaled(frame: np.ndarray, scale: float) -> Image.Image:
    img = Image.fromarray(np.asarray(frame, dtype=np.uint8))
    if scale != 1.0:
        size = (max(1, round(img.width * scale)), max(1, round(img.height * scale)))
        img = img.resize(size, Image.Resampling.LANCZOS)
    return img


def label_frame(frame: np.ndarray, text: str, driver: str) -> np.ndarray:
    """``frame`` ``(H, W, 3)`` uint8 with a caption band below it: ``text`` on the left, ``driver`` on
    the right in its colour (:data:`DRIVER_COLOURS`). Out: ``(H + CAPTION_HEIGHT, W, 3)`` uint8."""
    height, width = frame.shape[:2]
    canvas = Image.new("RGB", (width, height + CAPTION_HEIGHT), (24, 24, 24))
    canvas.paste(Image.fromarray(np.asarray(frame, dtype=np.uint8)), (0, 0))
    draw = ImageDraw.Draw(canvas)
    font = _font(CAPTION_HEIGHT - 8)
    middle = height + CAPTION_HEIGHT // 2
    draw.text((8, middle), text, fill=(235, 235, 235), font=font, anchor="lm")
    colour = DRIVER_COLOURS.get(driver, (235, 235, 235))
    right = width - 8
    draw.text((right, middle), driver, fill=colour, font=font, anchor="rm")
    box = draw.textbbox((right, middle), driver, font=font, anchor="rm")
    draw.rectangle((box[0] - 16, middle - 5, box[0] - 6, middle + 5), fill=colour)
    return np.asarray(canvas)


def _to_image(frame: np.ndarray, scale: float) -> Image.Image:
    # An adaptive palette per frame keeps the road's greys and the cars' colours apart.
    return _scaled(frame, scale).convert("P", palette=Image.Palette.ADAPTIVE, colors=256)


def scaled_frames(frames: list[np.ndarray], scale: float = DEFAULT_SCALE) -> np.ndarray:
    """``frames`` downscaled as :func:`write_gif` does, stacked: ``(T, h, w, 3)`` uint8 (a logger's video)."""
    return np.stack([np.asarray(_scaled(f, scale).convert("RGB")) for f in frames])


def write_gif(frames: list[np.ndarray], path: str | os.PathLike, fps: float = 10, scale: float = DEFAULT_SCALE) -> Path:
    """Write ``(H, W, 3)`` uint8 ``frames`` to ``path`` as a looping GIF, downscaled by ``scale``.

    Written to a temporary name, then renamed, so ``path`` is never a partial file.
    Identical consecutive frames (a car at rest) become one longer frame.
    """
    if not frames:
        raise ValueError("no frames to write")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [_to_image(f, scale) for f in frames]
    tmp = path.with_name(f".{path.name}.tmp.gif")
    # Pillow merges identical consecutive frames (adding their durations): timing is kept.
    images[0].save(tmp, save_all=True, append_images=images[1:], duration=max(1, round(1000 / fps)),
                   loop=0, optimize=False)
    os.replace(tmp, path)
    return path


def _captioned(frame: np.ndarray, scale: float, step: int, info: Mapping[str, Any], labels: bool) -> np.ndarray:
    """The render at ``scale``, captioned at that size (so the text stays sharp) when ``labels``."""
    scaled = np.asarray(_scaled(frame, scale).convert("RGB"))
    return label_frame(scaled, *frame_caption(step, info)) if labels else scaled


def record_episode_gif(
    policy: Policy,
    env_config: DrivingConfig | dict | None,
    scene_seed: int,
    path: str | os.PathLike,
    max_steps: int = 300,
    fps: float = 10,
    scale: float = DEFAULT_SCALE,
    keep_video: bool = False,
    labels: bool = True,
    wrap: Callable[[gym.Env], gym.Env] | None = None,
) -> dict[str, Any]:
    """Drive ``policy`` on scene ``scene_seed`` for at most ``max_steps`` steps and save a GIF.

    In: a policy (``reset()``, ``policy(obs, env) -> action``), the env config, the scene
    seed, the GIF path, the step cap, frames per second, the downscale factor, whether to return
    the frames too, whether to caption each frame (:func:`label_frame`: step, speed, who drives), and
    ``wrap``: a function wrapping the env before the episode (e.g.
    ``lambda env: InterventionWrapper(env, mentor, physics, selector)`` to film a takeover run; the
    policy then gets the wrapper). Sets ``SDL_VIDEODRIVER=dummy`` when unset (headless). Out: the last
    step's ``info`` plus ``episodic_return``, ``steps``, ``terminated``, ``truncated`` (env horizon or
    ``max_steps``), ``frames``, ``drivers`` (steps per driver) and ``path``; with ``keep_video``,
    ``video``: the GIF's frames as ``(T, h, w, 3)`` uint8 (:func:`scaled_frames`, captions included).
    """
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    env = make_gym_env(env_config, render_mode="rgb_array")
    if wrap is not None:
        env = wrap(env)
    drivers: dict[str, int] = {}
    try:
        policy.reset()
        obs, info = env.reset(options={"scene_seed": int(scene_seed)})
        frames = [_captioned(env.render(), scale, 0, info, labels)]
        episodic_return, steps = 0.0, 0
        terminated = truncated = False
        while not (terminated or truncated) and steps < max_steps:
            obs, reward, terminated, truncated, info = env.step(policy(obs, env))
            episodic_return += float(reward)
            steps += 1
            driver = driver_of(info)
            drivers[driver] = drivers.get(driver, 0) + 1
            frames.append(_captioned(env.render(), scale, steps, info, labels))
    finally:
        env.close()
    gif = write_gif(frames, path, fps=fps, scale=1.0)
    video = {"video": np.stack(frames)} if keep_video else {}
    return {
        **info,
        "episodic_return": episodic_return,
        "steps": steps,
        "terminated": bool(terminated),
        "truncated": bool(truncated or not terminated),
        "frames": len(frames),
        "drivers": drivers,
        "path": str(gif),
        **video,
    }
