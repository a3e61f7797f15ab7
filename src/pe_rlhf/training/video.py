"""Record one driving episode of any evaluation policy as a GIF (headless, Pillow only)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from pe_rlhf.envs import DrivingConfig, make_gym_env
from pe_rlhf.evaluation.policies import Policy


def _scaled(frame: np.ndarray, scale: float) -> Image.Image:
    img = Image.fromarray(np.asarray(frame, dtype=np.uint8))
    if scale != 1.0:
        size = (max(1, round(img.width * scale)), max(1, round(img.height * scale)))
        img = img.resize(size, Image.Resampling.LANCZOS)
    return img


def _to_image(frame: np.ndarray, scale: float) -> Image.Image:
    # An adaptive palette per frame keeps the road's greys and the cars' colours apart.
    return _scaled(frame, scale).convert("P", palette=Image.Palette.ADAPTIVE, colors=256)


def scaled_frames(frames: list[np.ndarray], scale: float = 0.5) -> np.ndarray:
    """``frames`` downscaled as :func:`write_gif` does, stacked: ``(T, h, w, 3)`` uint8 (a logger's video)."""
    return np.stack([np.asarray(_scaled(f, scale).convert("RGB")) for f in frames])


def write_gif(frames: list[np.ndarray], path: str | os.PathLike, fps: float = 10, scale: float = 0.5) -> Path:
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


def record_episode_gif(
    policy: Policy,
    env_config: DrivingConfig | dict | None,
    scene_seed: int,
    path: str | os.PathLike,
    max_steps: int = 300,
    fps: float = 10,
    scale: float = 0.5,
    keep_video: bool = False,
) -> dict[str, Any]:
    """Drive ``policy`` on scene ``scene_seed`` for at most ``max_steps`` steps and save a GIF.

    In: a policy (``reset()``, ``policy(obs, env) -> action``), the env config, the scene
    seed, the GIF path, the step cap, frames per second, the downscale factor, whether to return
    the frames too. Sets ``SDL_VIDEODRIVER=dummy`` when unset (headless). Out: the last step's ``info`` plus
    ``episodic_return``, ``steps``, ``terminated``, ``truncated`` (env horizon or
    ``max_steps``), ``frames`` and ``path``; with ``keep_video``, ``video``: the GIF's frames as
    ``(T, h, w, 3)`` uint8 (:func:`scaled_frames`).
    """
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    env = make_gym_env(env_config, render_mode="rgb_array")
    try:
        policy.reset()
        obs, info = env.reset(options={"scene_seed": int(scene_seed)})
        frames = [env.render()]
        episodic_return, steps = 0.0, 0
        terminated = truncated = False
        while not (terminated or truncated) and steps < max_steps:
            obs, reward, terminated, truncated, info = env.step(policy(obs, env))
            episodic_return += float(reward)
            steps += 1
            frames.append(env.render())
    finally:
        env.close()
    gif = write_gif(frames, path, fps=fps, scale=scale)
    video = {"video": scaled_frames(frames, scale)} if keep_video else {}
    return {
        **info,
        "episodic_return": episodic_return,
        "steps": steps,
        "terminated": bool(terminated),
        "truncated": bool(truncated or not terminated),
        "frames": len(frames),
        "path": str(gif),
        **video,
    }
