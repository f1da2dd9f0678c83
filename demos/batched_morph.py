"""Thousands of parameter values in one call, and a training loop through the morph.

Case C of the paper: a Wigley hull in a box of water, rotated by μ degrees about the
vertical (z) axis, μ in D = [-36°, 0°], the box fixed. The demo

1. sweeps D with ``--batch`` values of μ in one batched call — the boundary
   displacement of every μ is one (B, N_b, 3) tensor, the morph one contraction — for
   full IDW (every boundary node a control point, W stored) and for its POD reduction
   (Algorithm 3; the rotation's displacement lies in a two-dimensional space, so two
   modes reproduce IDW to round-off), and prints the morphs per second beside a
   Python loop of single calls and ``torch.func.vmap`` over a per-value family;
2. checks the batch: batched equals looped on a few μ, POD equals IDW, and counts
   the inverted tets of every μ of the sweep (the whole domain at once);
3. trains a small ``nn.Module`` whose forward contains the morph: an MLP that maps
   a requested sideways displacement of a probe point in the water ahead of the bow
   to the hull angle μ that produces it. The loss is measured on the morphed mesh, so
   every training step differentiates through the morph (amortised inverse design).

    python demos/batched_morph.py                          # paper-size mesh
    python demos/batched_morph.py --size small --out out/batched
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the demos' shared helpers

from _common import median_seconds

from torchmorph._atomic import atomic_output
from torchmorph.mesh import TetMesh
from torchmorph.mesh.quality import signed_volumes
from torchmorph.morph import MeshMorph
from torchmorph.paper import CASES, load_mesh
from torchmorph.pod import PODReducer

PROBE = (1.6, 0.0, 0.0)  # m: in the water, 0.35 m ahead of the bow (x = 1.25)


def volume_ratios(mesh: TetMesh, displacement: Tensor, chunk: int = 64) -> Tensor:
    """Smallest deformed / reference volume per field of a batch (B, N, 3) -> (B,)."""
    smallest = []
    with torch.no_grad():
        for start in range(0, displacement.shape[0], chunk):
            volumes = signed_volumes(mesh.points + displacement[start : start + chunk], mesh.tets)
            smallest.append((volumes / mesh.volumes).amin(-1))
    return torch.cat(smallest)


class InverseDesign(nn.Module):
    """Requested probe displacement -> hull angle μ, through an MLP; the forward also
    morphs the mesh at that μ and returns the probe's actual displacement.

    Parameters
    ----------
    morph : nn.Module
        Boundary displacement (B, N_b, 3) -> nodal displacement (B, N, 3).
    family : callable
        μ (B,) in degrees -> boundary displacement (B, N_b, 3).
    probe : int
        Node id whose sideways (y) displacement is requested.
    domain : (float, float)
        The range of angles.
    requests : (float, float)
        The range of probe displacements asked for.

    Notes
    -----
    Requests and angles are mapped to [-1, 1]; the network learns the correction
    to the straight line between the two ranges (a residual), which trains an order
    of magnitude further in the same number of steps than learning the whole map.
    """

    def __init__(
        self,
        morph: nn.Module,
        family: Callable[[Tensor], Tensor],
        probe: int,
        domain: tuple[float, float],
        requests: tuple[float, float],
        width: int = 32,
    ) -> None:
        super().__init__()
        self.morph = morph
        self.family = family
        self.probe = probe
        self.centre = 0.5 * (domain[0] + domain[1])
        self.half_width = 0.5 * (domain[1] - domain[0])
        self.request_centre = 0.5 * (requests[0] + requests[1])
        self.request_half_width = 0.5 * (requests[1] - requests[0])
        self.network = nn.Sequential(
            nn.Linear(1, width), nn.Tanh(), nn.Linear(width, width), nn.Tanh(), nn.Linear(width, 1)
        )

    def angle(self, request: Tensor) -> Tensor:
        """μ (B,) for requested probe displacements (B,)."""
        unit = ((request - self.request_centre) / self.request_half_width)[:, None]
        return self.centre + self.half_width * (unit + self.network(unit))[:, 0]

    def forward(self, request: Tensor) -> tuple[Tensor, Tensor]:
        mu = self.angle(request)
        displacement = self.morph(self.family(mu))  # (B, N, 3): the whole mesh, morphed
        return mu, displacement[:, self.probe, 1]


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--size",
        choices=("small", "paper"),
        default="paper",
        help="mesh size (default: %(default)s)",
    )
    parser.add_argument(
        "--out",
        default="out/batched_morph",
        help="directory for the PNG (default: %(default)s); '' writes nothing",
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1, ... (default cpu)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    parser.add_argument(
        "--batch",
        type=int,
        default=2000,
        help="parameter values in the batched call (default %(default)s)",
    )
    parser.add_argument(
        "--loop",
        type=int,
        default=20,
        help="single calls timed in the Python loop (default %(default)s)",
    )
    parser.add_argument(
        "--repeats", type=int, default=3, help="timed repeats of each batched call (median)"
    )
    parser.add_argument(
        "--train-steps", type=int, default=400, help="training steps of the inverse-design network"
    )
    parser.add_argument("--train-batch", type=int, default=128)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)"
    )
    parser.add_argument("--quiet", action="store_true", help="print nothing")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the demo; returns its numbers (rates, checks, training history)."""
    args = parse(argv)
    start = time.perf_counter()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch sees no CUDA device")
    dtype = getattr(torch, args.dtype)
    say = (lambda *a, **k: None) if args.quiet else print
    generator = torch.Generator().manual_seed(args.seed)
    spec = CASES["hull"]
    low, high = spec.domain

    # ------------------------------------------------------------------ offline
    mesh = load_mesh("hull", size=args.size).to(device=device, dtype=dtype)
    idw = MeshMorph(mesh)
    family = spec.family(idw)  # μ () or (B,) in degrees -> (N_b, 3) or (B, N_b, 3)
    training = spec.training_parameters(args.seed, dtype=dtype).to(device)
    reducer = PODReducer().fit(idw, family=family, parameters=training)
    setup = time.perf_counter() - start
    say(
        f"case C hull ({args.size}): {mesh.num_nodes} nodes, {mesh.num_tets} tets; IDW "
        f"{idw.num_controls} controls x {idw.num_interior} interior nodes "
        f"({idw.idw.mode}); POD-IDW {reducer.num_modes_} modes from {len(training)} "
        f"training angles; set-up {setup:.1f} s on {device}, {args.dtype}"
    )

    # ------------------------------------------------------------------ the sweep
    mus = torch.linspace(low, high, args.batch, dtype=dtype, device=device)
    result: dict[str, Any] = {
        "batch": args.batch,
        "num_modes": reducer.num_modes_,
        "setup_s": setup,
    }
    with torch.no_grad():
        boundary = family(mus)  # (B, N_b, 3)
        rates = {}
        fields = {}
        for name, morph in (("IDW", idw), ("POD-IDW", reducer)):
            seconds = median_seconds(lambda morph=morph: morph(boundary), args.repeats, device)
            fields[name] = morph(boundary)
            single = median_seconds(
                lambda morph=morph: [morph(family(mu)) for mu in mus[: args.loop]], 1, device
            )
            rates[name] = {
                "batched": args.batch / seconds,
                "looped": args.loop / single,
                "batched_s": seconds,
            }
        mapped_seconds = median_seconds(
            lambda: torch.func.vmap(lambda mu: idw(family(mu)))(mus), 1, device
        )
        mapped = torch.func.vmap(lambda mu: idw(family(mu)))(mus)
        rates["IDW"]["vmap"] = args.batch / mapped_seconds
        end_to_end = median_seconds(lambda: reducer(family(mus)), args.repeats, device)
        rates["POD-IDW"]["with family"] = args.batch / end_to_end
    result["rates"] = rates
    say(
        f"\n{args.batch} angles in [{low:g}°, {high:g}°], morphs per second "
        f"(output {args.batch} x {mesh.num_nodes} x 3):"
    )
    say(f"  {'':10s} {'batched call':>14s} {'Python loop':>14s} {'speed-up':>9s}")
    for name, rate in rates.items():
        say(
            f"  {name:10s} {rate['batched']:14,.0f} {rate['looped']:14,.0f} "
            f"{rate['batched'] / rate['looped']:8.0f}x"
        )
    say(
        f"  vmap over a per-angle family and IDW: {rates['IDW']['vmap']:,.0f} morphs/s; "
        f"POD-IDW including the family's evaluation: {rates['POD-IDW']['with family']:,.0f}"
        f" morphs/s"
    )

    # ------------------------------------------------------------------ checks
    with torch.no_grad():
        picks = torch.linspace(0, args.batch - 1, 5).round().long().tolist()
        looped_error = 0.0
        for name, morph in (("IDW", idw), ("POD-IDW", reducer)):
            for index in picks:
                single = morph(family(mus[index]))
                difference = (single - fields[name][index]).abs().max()
                looped_error = max(looped_error, float(difference))
        vmap_error = float((mapped - fields["IDW"]).abs().max())
        scale = fields["IDW"].flatten(1).norm(dim=1).clamp_min(torch.finfo(dtype).tiny)
        pod_error = (fields["POD-IDW"] - fields["IDW"]).flatten(1).norm(dim=1) / scale
        pod_error = pod_error[mus != 0]
        ratios = volume_ratios(mesh, fields["IDW"])
        inverted_angles = int((ratios <= 0).sum())
    result.update(
        looped_error=looped_error,
        vmap_error=vmap_error,
        pod_error=float(pod_error.max()),
        min_volume_ratio=float(ratios.min()),
        inverted_angles=inverted_angles,
    )
    say(
        f"\nbatched vs single calls, {len(picks)} angles: max |difference| "
        f"{looped_error:.1e} m; vmap vs batched {vmap_error:.1e} m; POD-IDW vs IDW: "
        f"relative error <= {result['pod_error']:.1e}"
    )
    say(
        f"over the sweep: smallest volume ratio {result['min_volume_ratio']:.3f}, angles "
        f"with inverted tets {inverted_angles} of {args.batch}"
    )

    # ------------------------------------------------------------------ training
    points = mesh.points
    probe_point = torch.tensor(PROBE, dtype=dtype, device=device)
    interior = idw.interior_nodes
    probe = int(interior[(points[interior] - probe_point).norm(dim=1).argmin()])
    with torch.no_grad():
        reachable = fields["POD-IDW"][:, probe, 1]
    low_request, high_request = float(reachable.min()), float(reachable.max())
    span = high_request - low_request
    torch.manual_seed(args.seed)
    model = InverseDesign(reducer, family, probe, spec.domain, (low_request, high_request))
    model = model.to(device=device, dtype=dtype)
    optimiser = torch.optim.Adam(model.network.parameters(), lr=1e-2)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, args.train_steps, eta_min=1e-4)
    losses = []
    say(
        f"\ntraining an MLP: requested sideways displacement of node {probe} at "
        f"{[round(float(c), 2) for c in points[probe]]} m (reachable "
        f"[{low_request:.4f}, {high_request:.4f}] m) -> hull angle; the loss is measured on "
        f"the morphed mesh (POD-IDW inside the forward)"
    )
    training_start = time.perf_counter()
    for step in range(args.train_steps):
        request = low_request + (high_request - low_request) * torch.rand(
            args.train_batch, generator=generator, dtype=dtype
        ).to(device)
        _, achieved = model(request)
        loss = ((achieved - request) / span).square().mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        losses.append(float(loss.detach()))
        if step % max(1, args.train_steps // 10) == 0 or step == args.train_steps - 1:
            say(f"  step {step:4d}  loss {losses[-1]:.3e}")
    training_s = time.perf_counter() - training_start
    with torch.no_grad():
        test = torch.linspace(low_request, high_request, 101, dtype=dtype, device=device)[1:-1]
        predicted, achieved = model(test)
        # the same angles through full IDW: the answer holds for the unreduced morph too
        checked = idw(family(predicted))[:, probe, 1]
        test_error = float((achieved - test).abs().max() / span)
        idw_error = float((checked - test).abs().max() / span)
    result.update(
        losses=losses,
        training_s=training_s,
        test_error=test_error,
        test_error_idw=idw_error,
        probe=probe,
    )
    say(
        f"trained in {training_s:.1f} s ({args.train_steps} steps of {args.train_batch}); "
        f"on 99 fresh requests the probe lands within {test_error:.1e} (POD-IDW) / "
        f"{idw_error:.1e} (full IDW) of the request, relative to the reachable range"
    )

    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        path = out / "batched_morph.png"
        plot(mus, reachable, ratios, losses, test, predicted, path)
        result["figure"] = path
        say(f"\nwrote {path}")
    result["total_s"] = time.perf_counter() - start
    say(f"total run time {result['total_s']:.1f} s")
    return result


def plot(mus, reachable, ratios, losses, test, predicted, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    mus, reachable, ratios = (x.detach().cpu() for x in (mus, reachable, ratios))
    axes[0].plot(mus, reachable * 1e3, label="batched sweep (POD-IDW)")
    axes[0].plot(predicted.cpu(), test.cpu() * 1e3, ".", ms=4, label="MLP: request -> angle")
    axes[0].set(
        xlabel="hull angle μ [°]",
        ylabel="probe y-displacement [mm]",
        title="probe ahead of the bow",
    )
    axes[1].plot(mus, ratios)
    axes[1].axhline(0.0, color="k", lw=0.8)
    axes[1].set(
        xlabel="hull angle μ [°]",
        ylabel="min V / V0",
        title=f"smallest volume ratio, {len(mus)} angles in one call",
    )
    axes[2].semilogy(losses)
    axes[2].set(xlabel="training step", ylabel="loss", title="training through the morph")
    for axis in axes:
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    figure.tight_layout()
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=120)
    plt.close(figure)


if __name__ == "__main__":
    main()
