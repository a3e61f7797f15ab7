"""Top-down pictures of whole scenes (road network, route, obstacles, traffic) with matplotlib."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def _outline(obj) -> np.ndarray:
    c, s = np.cos(obj.heading), np.sin(obj.heading)
    half_len, half_wid = obj.LENGTH / 2, obj.WIDTH / 2
    corners = np.array([[half_len, half_wid], [half_len, -half_wid], [-half_len, -half_wid],
                        [-half_len, half_wid], [half_len, half_wid]])
    return obj.position + corners @ np.array([[c, s], [-s, c]])


def draw_scene(env, ax) -> None:
    """Draw ``env``'s current road (grey), route (blue), obstacles (red), traffic (green), ego (black)."""
    net = env.road.network
    route_roads = set(env.route.segments)
    for _from, to_dict in net.graph.items():
        for _to, lanes in to_dict.items():
            on_route = (_from, _to) in route_roads
            for lane in lanes:
                s = np.linspace(0, lane.length, max(2, int(lane.length)))
                for lat in (-lane.width_at(0) / 2, lane.width_at(0) / 2):
                    pts = np.array([lane.position(si, lat) for si in s])
                    ax.plot(pts[:, 0], pts[:, 1], color="tab:blue" if on_route else "0.6", lw=0.5)
    for obj in env.road.objects:
        o = _outline(obj)
        ax.fill(o[:, 0], o[:, 1], color="tab:red")
    for v in env.road.vehicles:
        o = _outline(v)
        ax.fill(o[:, 0], o[:, 1], color="black" if v is env.vehicle else "tab:green")
    end = env.route.checkpoints(len(env.route.segments) - 1, 1)[0]
    ax.plot(*end, marker="*", color="gold", markersize=12, markeredgecolor="k")
    ax.set_aspect("equal")
    ax.invert_yaxis()  # highway-env's screen convention: y points down
    ax.set_title(f"scene {env.scene_seed}: {', '.join(env.current_scene.blocks)}", fontsize=7)
    ax.axis("off")


def plot_scenes(env, seeds, path: str, columns: int = 4) -> None:
    """Save a grid of top-down scene pictures for ``seeds`` to ``path`` (PNG)."""
    rows = int(np.ceil(len(seeds) / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(4 * columns, 3.2 * rows))
    for ax, seed in zip(np.atleast_1d(axes).ravel(), seeds):
        env.reset(options={"scene_seed": int(seed)})
        draw_scene(env, ax)
    for ax in np.atleast_1d(axes).ravel()[len(seeds):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
