"""ms per update: one ``PERLHFLoss`` update vs one torchrl ``SACLoss`` update, same process.

An update is: forward on a batch, backward of the summed ``loss_*`` terms, an Adam step on all
the loss module's parameters, and a Polyak step (tau=0.005) of the targets, both as the learners take them
(``make_adam``: fused Adam; ``ForeachSoftUpdate``). Both losses use the same
networks (``make_actor`` / ``make_qvalue``, 256x256 MLPs), obs dim 250 (the real env's), batch
1024, 2 critics; the PE-RLHF batch has ~25% takeover rows. PE-RLHF is timed twice: as shipped
(``perlhf``: ``fused_critics=True``) and through its critic modules (``perlhf_modules``:
``fused_critics=False``, the path before issue 20) and with torch's default Adam and TorchRL's
``SoftUpdate`` (``perlhf_torch_steps``); ``--no-reference`` skips both.

These machines are shared and noisy, so the losses are interleaved update by update (ABBA order
in each round) on ``--threads`` threads, every update is timed on its own (wall and process CPU
time), and the comparison uses medians: the median update of each loss over all rounds, and the
median over rounds of the per-round ratio to SAC.

    python benchmarks/update_speed.py [--rounds 9] [--updates 4] [--precision fp32|bf16] [--device cpu|cuda]
                                      [--json out.json]

``--device cuda``: the losses, their optimisers and the batch on the GPU, each update timed up to a
``torch.cuda.synchronize()`` (what ``optim.device=cuda`` runs); the matmul ceiling is then the GPU's.

Also reported: each update's floating-point work (torch's FLOP formulas, ``torch.utils.flop_counter``: forward,
backward; Adam and the Polyak step are not matrix work and are not counted), the FLOP rate it achieves, and
this CPU's matmul ceiling on the same threads (a 1024x1024 product in fp32 and bf16, best of a few): what
share of the machine an update uses, and whether a ratio above 1 is extra work or extra overhead.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
import warnings

import torch
from tensordict import TensorDict
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import flop_registry
from torchrl.objectives import SACLoss, SoftUpdate

from pe_rlhf.modules import make_actor, make_qvalue
from pe_rlhf.objectives import ForeachSoftUpdate, PERLHFLoss, make_adam
from pe_rlhf.objectives.perlhf import make_transitions

ACTION_DIM = 2
RATIO_TARGET = 1.25


def make_batch(batch: int, obs_dim: int, intervention_rate: float, seed: int = 0) -> TensorDict:
    """A replay-buffer-like batch with every key either loss reads."""
    g = torch.Generator().manual_seed(seed)
    agent = torch.rand(batch, ACTION_DIM, generator=g) * 2 - 1
    intervention = torch.rand(batch, 1, generator=g) < intervention_rate
    behavior = torch.where(intervention, torch.rand(batch, ACTION_DIM, generator=g) * 2 - 1, agent)
    start = intervention & (torch.rand(batch, 1, generator=g) < 0.3)
    terminated = torch.rand(batch, 1, generator=g) < 0.01
    return make_transitions(torch.rand(batch, obs_dim, generator=g), torch.rand(batch, obs_dim, generator=g),
                            agent, behavior, intervention, start, terminated, torch.randn(batch, 1, generator=g))


class Updater:
    """Loss + Adam over all its parameters + a Polyak target step: one ``step()`` is one full update.

    ``steps="library"``: the learners' own steps (``pe_rlhf.objectives.make_adam``, fused where it can be, and
    ``ForeachSoftUpdate``); ``"torch"``: ``torch.optim.Adam``'s default and TorchRL's ``SoftUpdate``."""

    def __init__(self, loss, lr: float = 3e-4, precision: str = "fp32", steps: str = "library",
                 device: str = "cpu"):
        self.loss = loss.to(device)
        self.device = torch.device(device)
        if steps == "library":
            self.optim = make_adam(loss.parameters(), lr=lr)
            self.target = ForeachSoftUpdate(loss, tau=0.005)
        else:
            self.optim = torch.optim.Adam(loss.parameters(), lr=lr)
            self.target = SoftUpdate(loss, tau=0.005)
        self.precision = precision

    def step(self, batch: TensorDict) -> None:
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            out = self.loss(batch)
        total = sum(v for k, v in out.items() if k.startswith("loss_"))
        self.optim.zero_grad(set_to_none=True)
        total.backward()
        self.optim.step()
        self.target.step()
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)  # the update is done when the GPU is


def build(obs_dim: int, hidden: tuple[int, ...], intervention_critics: int = 1,
          precision: str = "fp32", reference: bool = True, device: str = "cpu") -> dict[str, Updater]:
    """``sac``, ``perlhf`` (the default, fused critics) and, with ``reference``, ``perlhf_modules``
    (``fused_critics=False``: one module call per critic and action set, the path before issue 20) and
    ``perlhf_torch_steps`` (the default loss with torch's Adam and TorchRL's ``SoftUpdate``). All but the last
    take the learners' own optimiser and target steps."""
    torch.manual_seed(0)
    sac = SACLoss(make_actor(obs_dim, hidden=hidden), make_qvalue(obs_dim, hidden=hidden), num_qvalue_nets=2,
                  loss_function="l2", target_entropy=-float(ACTION_DIM))
    updaters = {"sac": Updater(sac, precision=precision, device=device)}
    for name, fused in (("perlhf", True), ("perlhf_modules", False))[:2 if reference else 1]:
        torch.manual_seed(0)
        perlhf = PERLHFLoss(make_actor(obs_dim, hidden=hidden), make_qvalue(obs_dim, hidden=hidden),
                            make_qvalue(obs_dim, hidden=hidden), num_qvalue_nets=2, action_dim=ACTION_DIM,
                            num_intervention_qvalue_nets=intervention_critics, fused_critics=fused)
        updaters[name] = Updater(perlhf, precision=precision, device=device)
    if reference:
        torch.manual_seed(0)
        perlhf = PERLHFLoss(make_actor(obs_dim, hidden=hidden), make_qvalue(obs_dim, hidden=hidden),
                            make_qvalue(obs_dim, hidden=hidden), num_qvalue_nets=2, action_dim=ACTION_DIM,
                            num_intervention_qvalue_nets=intervention_critics)
        updaters["perlhf_torch_steps"] = Updater(perlhf, precision=precision, steps="torch", device=device)
    return updaters


class CountFlops(TorchDispatchMode):
    """Adds up torch's FLOP formulas (``flop_registry``: matrix products, convolutions) of every op run under
    it. ``FlopCounterMode`` itself cannot be used: its module tracker tests TensorDict modules for truth."""

    def __init__(self):
        super().__init__()
        self.total = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        formula = flop_registry.get(func._overloadpacket)
        if formula is not None:
            self.total += int(formula(*args, **kwargs, out_val=out))
        return out


def update_flops(updater: Updater, batch: TensorDict) -> int:
    """Floating-point operations of one update's forward and backward (matrix products dominate)."""
    with CountFlops() as counter:
        updater.step(batch.copy())
    return counter.total


def matmul_ceiling(threads: int, dtype: torch.dtype, size: int = 1024, repeats: int = 10,
                   device: str = "cpu") -> float:
    """GFLOP/s of a ``size x size`` linear layer (``F.linear``, the networks' own path) on ``threads`` threads
    or on ``device``: best of 5 timings of ``repeats`` (the caller has set the thread count)."""
    x, w, b = (torch.randn(size, size).to(device, dtype), torch.randn(size, size).to(device, dtype),
               torch.randn(size).to(device, dtype))
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    for _ in range(2):
        torch.nn.functional.linear(x, w, b)
    best = float("inf")
    for _ in range(5):
        sync()
        t = time.perf_counter()
        for _ in range(repeats):
            torch.nn.functional.linear(x, w, b)
        sync()
        best = min(best, (time.perf_counter() - t) / repeats)
    return 2 * size ** 3 / best / 1e9


def time_update(updater: Updater, batch: TensorDict) -> tuple[float, float]:
    """(wall, process CPU) ms of one update. A fresh shallow copy: SACLoss writes ``td_error`` into it."""
    batch = batch.copy()
    wall, cpu = time.perf_counter(), time.process_time()
    updater.step(batch)
    return 1000 * (time.perf_counter() - wall), 1000 * (time.process_time() - cpu)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--obs-dim", type=int, default=250)
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--intervention-rate", type=float, default=0.25)
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--updates", type=int, default=4, help="updates per loss per round")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--intervention-critics", type=int, default=1,
                        help="copies of Q_int in PERLHFLoss (1 = the paper's single critic, the default; "
                             "2 = the authors' twin)")
    parser.add_argument("--precision", choices=["fp32", "bf16"], default="fp32",
                        help="bf16: the losses' forward under bf16 autocast, as optim.precision=bf16")
    parser.add_argument("--no-reference", dest="reference", action="store_false",
                        help="skip PERLHFLoss(fused_critics=False) (timed by default, interleaved with the others)")
    parser.add_argument("--device", default="cpu", help="cpu | cuda | cuda:N: where the losses and the batch live")
    parser.add_argument("--json", default=None, help="write the results here")
    args = parser.parse_args(argv)
    if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
        parser.error(f"--device {args.device}: torch sees no CUDA device here")

    warnings.filterwarnings("ignore", category=UserWarning)  # torchrl's target-updater notes
    torch.set_num_threads(args.threads)
    batch = make_batch(args.batch, args.obs_dim, args.intervention_rate).to(args.device)
    updaters = build(args.obs_dim, (args.hidden, args.hidden), args.intervention_critics, args.precision,
                     args.reference, args.device)
    variants = [name for name in updaters if name != "sac"]
    for _ in range(args.warmup):
        for updater in updaters.values():
            updater.step(batch.copy())
    flops = {name: update_flops(u, batch) for name, u in updaters.items()}
    ceiling = {"fp32": matmul_ceiling(args.threads, torch.float32, device=args.device),
               "bf16": matmul_ceiling(args.threads, torch.bfloat16, device=args.device)}

    wall: dict[str, list[list[float]]] = {name: [] for name in updaters}
    cpu: dict[str, list[list[float]]] = {name: [] for name in updaters}
    ratios: dict[str, list[float]] = {name: [] for name in variants}
    cpu_ratios: dict[str, list[float]] = {name: [] for name in variants}
    for r in range(args.rounds):
        for name in updaters:
            wall[name].append([])
            cpu[name].append([])
        for i in range(args.updates):
            order = list(updaters) if i % 2 == 0 else list(reversed(updaters))  # ABBA: no first-mover bias
            for name in order:
                w, c = time_update(updaters[name], batch)
                wall[name][-1].append(w)
                cpu[name][-1].append(c)
        med = {name: statistics.median(wall[name][-1]) for name in updaters}
        med_cpu = {name: statistics.median(cpu[name][-1]) for name in updaters}
        for name in variants:
            ratios[name].append(med[name] / med["sac"])
            cpu_ratios[name].append(med_cpu[name] / med_cpu["sac"])
        print(f"round {r}: SAC {med['sac']:7.1f} ms" + "".join(
            f"  {name} {med[name]:7.1f} ms ratio {ratios[name][-1]:.2f} (CPU {cpu_ratios[name][-1]:.2f})"
            for name in variants))

    def overall(times: dict[str, list[list[float]]], name: str) -> float:
        return statistics.median(t for round_ in times[name] for t in round_)

    ms = {name: overall(wall, name) for name in updaters}
    achieved = {name: flops[name] / ms[name] / 1e6 for name in updaters}
    result = {
        "config": {k: v for k, v in vars(args).items() if k != "json"},
        "torch": torch.__version__,
        "device": torch.cuda.get_device_name(args.device) if torch.device(args.device).type == "cuda" else "cpu",
        "actual_intervention_rate": float(batch["next", "intervention"].float().mean()),
        "sac_ms_median": ms["sac"],
        "perlhf_ms_median": ms["perlhf"],
        "ratio_of_medians": ms["perlhf"] / ms["sac"],
        "ratio_median_of_rounds": statistics.median(ratios["perlhf"]),
        "sac_cpu_ms_median": overall(cpu, "sac"),
        "perlhf_cpu_ms_median": overall(cpu, "perlhf"),
        "cpu_ratio_median_of_rounds": statistics.median(cpu_ratios["perlhf"]),
        "ratio_target": RATIO_TARGET,
        "gflop_per_update": {name: f / 1e9 for name, f in flops.items()},
        "flop_ratio": flops["perlhf"] / flops["sac"],
        "achieved_gflops": achieved,
        "matmul_ceiling_gflops": ceiling,
        "share_of_ceiling": {name: a / ceiling[args.precision] for name, a in achieved.items()},
        **{f"{name}_ms_per_update": wall[name] for name in updaters},
    }
    if "perlhf_modules" in updaters:  # the reference path, same run
        result["reference"] = {
            "perlhf_modules_ms_median": ms["perlhf_modules"],
            "ratio_of_medians": ms["perlhf_modules"] / ms["sac"],
            "ratio_median_of_rounds": statistics.median(ratios["perlhf_modules"]),
            "cpu_ratio_median_of_rounds": statistics.median(cpu_ratios["perlhf_modules"]),
            "flop_ratio": flops["perlhf_modules"] / flops["sac"],
            "speedup_of_fused": ms["perlhf_modules"] / ms["perlhf"],
            "perlhf_torch_steps_ms_median": ms["perlhf_torch_steps"],
            "speedup_of_library_steps": ms["perlhf_torch_steps"] / ms["perlhf"],
        }
    for name in variants:
        print(f"median: SAC {ms['sac']:.1f} ms/update, {name} {ms[name]:.1f} ms/update, "
              f"ratio {ms[name] / ms['sac']:.2f}, median of per-round ratios {statistics.median(ratios[name]):.2f} "
              f"(CPU time {statistics.median(cpu_ratios[name]):.2f}); target <= {RATIO_TARGET}")
    print("work: " + ", ".join(f"{name} {flops[name] / 1e9:.2f} GFLOP ({achieved[name]:.0f} GFLOP/s)"
                                for name in updaters)
          + f" an update; {args.precision} matmul ceiling {ceiling[args.precision]:.0f} GFLOP/s "
          f"(fp32 {ceiling['fp32']:.0f}, bf16 {ceiling['bf16']:.0f})")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return result


if __name__ == "__main__":
    main()
