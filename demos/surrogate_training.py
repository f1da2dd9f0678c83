"""A surrogate trained on meshes morphed on the fly: every batch one batched morph, no files.

Case B of the paper (the wing of case A in a tunnel, its root on the wall z = 0, the
tunnel walls fixed), with the wing deformed by three parameters μ, s = z / L the span
fraction (the family of ``shape_optimisation.py``):

    bending   δy = μ1 s² + μ2 s³                     (metres at the tip)
    twist     rotation of each section about its quarter chord by μ3 s (degrees)

The fluid mesh follows by POD-ESIDW (Algorithm 2 with the case's ESIDW selection,
reduced by Algorithm 3). A small network learns μ -> the volumetric strain of every
fluid cell, ``V(μ) / V0 - 1`` (how much the morph squeezes or stretches each tet: a
field of the morphed geometry). The network is an MLP on μ (normalised to [-1, 1]³)
with a linear decoder to the T cell values; its loss is the mean squared error,
scaled by the field's spread.

Each training batch is generated inside the loop: B fresh values of μ, their boundary
displacements as one (B, N_b, 3) tensor, one batched POD-ESIDW morph of the B meshes,
the cell volumes of all of them at once. Beside it the same training reads its
batches from a bank of meshes morphed beforehand (a (M, N, 3) tensor of
displacements, indexed per batch; the cell volumes are computed in the loop alike),
so the two loops differ only by the morph; they step in turn, each timed on its own
steps. The demo prints batches per second of both loops, the morph's share of a step,
and the surrogate's error on held-out μ (relative L2 error of the strain field, and
the largest error in V / V0).

What it shows, on one CPU thread: the reduced morph of a batch is about 2 % of a
training step (small mesh, 8 meshes a batch: 0.3 ms of 13 ms; paper-size mesh, 16 a
batch: 8 ms of 0.6 s), far less than the cells' volumes of the batch, so meshes made on
the fly cost about what reading stored ones costs (1.01-1.08x the time per batch), with
fresh μ in every batch; the full ESIDW morph (no POD) of the batch would take about half
a step at the paper size. Timings on a GPU are not part of this record.

    python demos/surrogate_training.py                      # paper-size mesh
    python demos/surrogate_training.py --size small --out out/surrogate
    python demos/surrogate_training.py --device cuda
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

from _common import median_seconds, set_threads, synchronise
from shape_optimisation import wing_family

from torchmorph._atomic import atomic_output
from torchmorph.mesh import Mesh, TetMesh
from torchmorph.mesh.quality import signed_volumes
from torchmorph.morph import MeshMorph
from torchmorph.paper import CASES, load_mesh
from torchmorph.pod import PODReducer

#: The parameter box: μ1, μ2 in metres (tip deflection of each bending shape), μ3 in
#: degrees (tip twist). In it the small mesh's cells keep half their volume or more, the
#: paper-size mesh's a fifth (the demo prints the smallest V / V0 it meets).
PARAMETER_BOX = ((-0.4, 0.4), (-0.3, 0.3), (-6.0, 6.0))


def tunnel_wing_family(morph: MeshMorph, mesh: Mesh) -> Callable[[Tensor], Tensor]:
    """μ (B, 3) -> boundary displacement (B, N_b, 3): the wing's nodes bend and twist,
    the tunnel's walls stay (rows ordered as ``morph.boundary_nodes``)."""
    on_wing = torch.isin(morph.boundary_nodes, mesh.node_set("wing"))
    moving = wing_family(morph.boundary_points)
    mask = on_wing.to(morph.boundary_points.dtype)[:, None]

    def family(mu: Tensor) -> Tensor:
        return moving(mu) * mask

    return family


class CellStrain:
    """The volumetric strain ``V / V0 - 1`` of every tet of a batch of morphed meshes.

    Parameters
    ----------
    mesh : TetMesh
        The reference mesh (its points, tets and volumes V0).
    """

    def __init__(self, mesh: TetMesh) -> None:
        self.points = mesh.points
        self.tets = mesh.tets
        self.reference_volumes = mesh.volumes

    def __call__(self, displacement: Tensor) -> Tensor:
        """(B, N, 3) nodal displacements -> (B, T) strains."""
        volumes = signed_volumes(self.points + displacement, self.tets)
        return volumes / self.reference_volumes - 1.0


class Surrogate(nn.Module):
    """μ (B, k) -> a field of T values per μ (B, T): an MLP on μ mapped to [-1, 1]^k,
    then a linear decoder from its features and μ itself (the decoder's columns play
    the part of learned modes; the term linear in μ is there from the first step).

    Parameters
    ----------
    box : sequence of (low, high)
        The parameter box, one pair per parameter.
    num_outputs : int
        T, the values of the field.
    width : int
        Hidden width of the MLP (two hidden SiLU layers).
    mean, scale : Tensor, shape (T,) and ()
        The field's mean and spread: the network predicts ``(field - mean) / scale``.
    """

    centre: Tensor
    half_width: Tensor
    mean: Tensor
    scale: Tensor

    def __init__(
        self,
        box: Sequence[tuple[float, float]],
        num_outputs: int,
        *,
        width: int,
        mean: Tensor,
        scale: Tensor,
    ) -> None:
        super().__init__()
        low = torch.tensor([bounds[0] for bounds in box])
        high = torch.tensor([bounds[1] for bounds in box])
        self.register_buffer("centre", (low + high) / 2)
        self.register_buffer("half_width", (high - low) / 2)
        self.register_buffer("mean", mean.detach().clone())
        self.register_buffer("scale", scale.detach().clone())
        self.features = nn.Sequential(
            nn.Linear(len(box), width), nn.SiLU(), nn.Linear(width, width), nn.SiLU()
        )
        self.decoder = nn.Linear(width + len(box), num_outputs)

    def normalised(self, mu: Tensor) -> Tensor:
        """The network's output for μ (B, k): the field minus its mean, over its spread."""
        unit = (mu - self.centre) / self.half_width
        return self.decoder(torch.cat([self.features(unit), unit], -1))

    def forward(self, mu: Tensor) -> Tensor:
        return self.mean + self.scale * self.normalised(mu)


def sample_parameters(count: int, generator: torch.Generator, dtype: torch.dtype) -> Tensor:
    """``count`` values of μ drawn uniformly in :data:`PARAMETER_BOX`, shape (count, 3)."""
    low = torch.tensor([bounds[0] for bounds in PARAMETER_BOX], dtype=dtype)
    high = torch.tensor([bounds[1] for bounds in PARAMETER_BOX], dtype=dtype)
    return low + (high - low) * torch.rand(
        count, len(PARAMETER_BOX), generator=generator, dtype=dtype
    )


def box_corners(dtype: torch.dtype) -> Tensor:
    """The 2^k corners of :data:`PARAMETER_BOX`, shape (2^k, k)."""
    grids = torch.meshgrid(
        *(torch.tensor(bounds, dtype=dtype) for bounds in PARAMETER_BOX), indexing="ij"
    )
    return torch.stack([g.reshape(-1) for g in grids], -1)


class TrainingLoop:
    """A surrogate, its Adam optimiser (cosine schedule over ``steps``) and its source
    of batches ``batches() -> (μ, field)``; :meth:`step` trains on one batch.

    The loss is the mean squared error of the scaled field. ``losses`` and ``seconds``
    (the wall time of the steps, the making of the batches included) accumulate.
    """

    def __init__(
        self,
        surrogate: Surrogate,
        batches: Callable[[], tuple[Tensor, Tensor]],
        *,
        steps: int,
        learning_rate: float,
        device: torch.device,
    ) -> None:
        self.surrogate = surrogate
        self.batches = batches
        self.device = device
        self.optimiser = torch.optim.Adam(surrogate.parameters(), lr=learning_rate)
        self.schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
            self.optimiser, steps, eta_min=learning_rate / 100
        )
        self.losses: list[Tensor] = []
        self.seconds = 0.0

    def step(self) -> None:
        synchronise(self.device)
        start = time.perf_counter()
        mu, field = self.batches()
        target = (field - self.surrogate.mean) / self.surrogate.scale
        loss = (self.surrogate.normalised(mu) - target).square().mean()
        self.optimiser.zero_grad()
        loss.backward()
        self.optimiser.step()
        self.schedule.step()
        self.losses.append(loss.detach())
        synchronise(self.device)
        self.seconds += time.perf_counter() - start


def held_out_errors(surrogate: Surrogate, mu: Tensor, field: Tensor) -> dict[str, float]:
    """The surrogate against the morphed meshes' field (B, T) at μ (B, k): the relative
    L2 error over all of them (``relative``), and the largest error in V / V0 of any
    cell (``ratio_max``)."""
    with torch.no_grad():
        error = surrogate(mu) - field
    return {
        "relative": float(error.norm() / field.norm()),
        "ratio_max": float(error.abs().max()),
    }


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
        default="out/surrogate_training",
        help="directory for the PNG (default: %(default)s); '' writes nothing",
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1, ... (default cpu)")
    parser.add_argument(
        "--dtype",
        choices=("float32", "float64"),
        default="float32",
        help="dtype of the morph and the network (default %(default)s; the POD is fitted "
        "in float64)",
    )
    parser.add_argument(
        "--batch", type=int, default=16, help="meshes per training batch (default %(default)s)"
    )
    parser.add_argument(
        "--steps", type=int, default=800, help="training steps of each loop (default %(default)s)"
    )
    parser.add_argument(
        "--bank",
        type=int,
        default=512,
        help="meshes morphed beforehand for the precomputed loop (default %(default)s)",
    )
    parser.add_argument(
        "--held-out", type=int, default=64, help="held-out values of μ (default %(default)s)"
    )
    parser.add_argument(
        "--width", type=int, default=64, help="hidden width of the network (default %(default)s)"
    )
    parser.add_argument(
        "--lr", type=float, default=1e-2, help="Adam's learning rate (default %(default)s)"
    )
    parser.add_argument(
        "--train-pod",
        type=int,
        default=60,
        help="POD training values of μ (default %(default)s)",
    )
    parser.add_argument(
        "--repeats", type=int, default=20, help="timed repeats of the morph alone (median)"
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of the selection, μ and the network"
    )
    parser.add_argument(
        "--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)"
    )
    parser.add_argument("--quiet", action="store_true", help="print nothing")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the demo; returns its numbers (rates, the morph's share, errors, losses)."""
    args = parse(argv)
    start = time.perf_counter()
    set_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda asked for, but torch sees no CUDA device")
    dtype = getattr(torch, args.dtype)
    say = (lambda *a, **k: None) if args.quiet else print
    generator = torch.Generator().manual_seed(args.seed)

    # ------------------------------------------------------------------ offline
    spec = CASES["fluid-wing"]
    reference = load_mesh("fluid-wing", size=args.size)
    assert isinstance(reference, TetMesh)  # case B's tunnel: tetrahedra
    esidw = MeshMorph(reference, spec.plan(), generator=generator)  # selection on the CPU
    training = sample_parameters(args.train_pod, generator, torch.float64)
    training = torch.cat([box_corners(torch.float64), training])
    reducer = PODReducer(energy_tolerance=1e-8)
    reducer.fit(esidw, family=tunnel_wing_family(esidw, reference), parameters=training)
    mesh = reference.to(device=device, dtype=dtype)
    assert isinstance(mesh, TetMesh)
    esidw = esidw.to(device=device, dtype=dtype)
    reducer = reducer.to(device=device, dtype=dtype)
    family = tunnel_wing_family(esidw, mesh)
    strain = CellStrain(mesh)
    setup = time.perf_counter() - start
    say(
        f"case B tunnel ({args.size}): {mesh.num_nodes} nodes, {mesh.num_tets} tets, "
        f"{esidw.num_boundary} boundary nodes; ESIDW {esidw.num_controls} control points; "
        f"POD {reducer.num_modes_} modes from {len(training)} values of μ; set-up "
        f"{setup:.1f} s on {device}, {args.dtype}"
    )

    def morphed_strain(mu: Tensor) -> Tensor:
        """One batched POD-ESIDW morph of every μ (B, 3), then the cells' strain (B, T)."""
        return strain(reducer(family(mu)))

    def draw(count: int) -> Tensor:
        return sample_parameters(count, generator, dtype).to(device)

    # the bank of precomputed meshes, the held-out set, the field's scale
    with torch.no_grad():
        synchronise(device)
        bank_start = time.perf_counter()
        bank_mu = draw(args.bank)
        bank = torch.cat([reducer(family(chunk)) for chunk in bank_mu.split(args.batch)])
        synchronise(device)
        bank_s = time.perf_counter() - bank_start
        held_mu = draw(args.held_out)
        held_strain = morphed_strain(held_mu)
        held_full = strain(esidw(family(held_mu)))  # the same μ through full ESIDW
        pod_error = float((held_strain - held_full).norm() / held_full.norm())
        corners = morphed_strain(box_corners(dtype).to(device))
        bank_strain = strain(bank)
        mean, scale = bank_strain.mean(0), bank_strain.std()
    smallest_ratio = float(1.0 + torch.cat([corners, held_strain, bank_strain]).min())
    say(
        f"bank: {args.bank} meshes morphed beforehand in {bank_s:.2f} s "
        f"({bank.numel() * bank.element_size() / 2**20:.0f} MiB); smallest V / V0 over the "
        f"box's corners, the bank and the held-out set {smallest_ratio:.3f}"
    )

    # ------------------------------------------------------------------ timing
    mu_batch = draw(args.batch)
    with torch.no_grad():
        morph_s = median_seconds(lambda: reducer(family(mu_batch)), args.repeats, device)
        full_morph_s = median_seconds(lambda: esidw(family(mu_batch)), args.repeats, device)
        strain_s = median_seconds(lambda: strain(bank[: args.batch]), args.repeats, device)

    # ------------------------------------------------------------------ training
    def on_the_fly() -> tuple[Tensor, Tensor]:
        mu = draw(args.batch)
        with torch.no_grad():
            return mu, morphed_strain(mu)

    picks = torch.Generator(device=device).manual_seed(args.seed + 1)

    def precomputed() -> tuple[Tensor, Tensor]:
        rows = torch.randint(args.bank, (args.batch,), generator=picks, device=device)
        with torch.no_grad():
            return bank_mu[rows], strain(bank[rows])

    # the two loops step in turn, each timed on its own steps: a load that comes and goes
    # on the machine slows both alike
    loops: dict[str, TrainingLoop] = {}
    for name, batches in (("morph in the loop", on_the_fly), ("precomputed meshes", precomputed)):
        torch.manual_seed(args.seed)  # the same initial network for both loops
        surrogate = Surrogate(
            PARAMETER_BOX, mesh.num_tets, width=args.width, mean=mean, scale=scale
        ).to(device=device, dtype=dtype)
        loops[name] = TrainingLoop(
            surrogate, batches, steps=args.steps, learning_rate=args.lr, device=device
        )
    for _ in range(args.steps):
        for loop in loops.values():
            loop.step()
    rates = {name: args.steps / loop.seconds for name, loop in loops.items()}
    held_out = {
        name: held_out_errors(loop.surrogate, held_mu, held_strain) for name, loop in loops.items()
    }
    losses = {
        name: [float(value) for value in torch.stack(loop.losses).cpu()]
        for name, loop in loops.items()
    }
    inside, outside = (1.0 / rates[name] for name in loops)  # seconds per step
    result: dict[str, Any] = {
        "num_nodes": mesh.num_nodes,
        "num_tets": mesh.num_tets,
        "num_modes": reducer.num_modes_,
        "num_controls": esidw.num_controls,
        "setup_s": setup,
        "bank_s": bank_s,
        "batches_per_s": rates,
        "meshes_per_s": {name: rate * args.batch for name, rate in rates.items()},
        "step_s": {name: 1.0 / rate for name, rate in rates.items()},
        "morph_s": morph_s,
        "full_morph_s": full_morph_s,
        "strain_s": strain_s,
        "morph_share": morph_s / inside,
        "slowdown": inside / outside,
        "held_out": held_out,
        "losses": losses,
        "pod_error": pod_error,
        "smallest_volume_ratio": smallest_ratio,
    }
    say(
        f"\ntraining {args.steps} batches of {args.batch} meshes each, the two loops in turn: "
        f"an MLP μ -> the strain V / V0 - 1 of {mesh.num_tets} cells"
    )
    say(
        f"  {'':20s} {'batches/s':>10s} {'meshes/s':>10s} {'held-out error':>15s} "
        f"{'max |ΔV/V0|':>12s}"
    )
    for name, rate in rates.items():
        errors = held_out[name]
        say(
            f"  {name:20s} {rate:10,.1f} {rate * args.batch:10,.0f} "
            f"{errors['relative']:15.2%} {errors['ratio_max']:12.1e}"
        )
    say(
        f"a step takes {inside * 1e3:.1f} ms with the morph in the loop, {outside * 1e3:.1f} ms "
        f"reading precomputed meshes ({result['slowdown']:.2f}x); of it the batched POD-ESIDW "
        f"morph of {args.batch} meshes {morph_s * 1e3:.2f} ms ({result['morph_share']:.1%}), "
        f"the cells' volumes {strain_s * 1e3:.1f} ms; full ESIDW (no POD) would take "
        f"{full_morph_s * 1e3:.1f} ms. The morph in the loop sees fresh μ in every batch, "
        f"the precomputed loop the same {args.bank} meshes again and again."
    )
    say(
        f"held-out error: relative L2 of the strain over {args.held_out} fresh μ (for scale: "
        f"the POD-ESIDW strain differs from full ESIDW's by {pod_error:.2%})"
    )

    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        path = out / "surrogate_training.png"
        with torch.no_grad():
            predicted = loops["morph in the loop"].surrogate(held_mu)
        plot(losses, rates, held_strain, predicted, path)
        result["figure"] = path
        say(f"\nwrote {path}")
    result["total_s"] = time.perf_counter() - start
    say(f"total run time {result['total_s']:.1f} s")
    return result


def plot(
    losses: dict[str, list[float]],
    rates: dict[str, float],
    truth: Tensor,
    predicted: Tensor,
    path: Path,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, values in losses.items():
        axes[0].semilogy(values, label=f"{name} ({rates[name]:.1f} batches/s)")
    axes[0].set(xlabel="training step", ylabel="scaled MSE", title="training loss")
    axes[0].legend(fontsize=8)
    truth, predicted = truth.cpu().flatten(), predicted.cpu().flatten()
    spread = float(truth.abs().max())
    axes[1].plot(truth, predicted, ".", ms=1, alpha=0.3)
    axes[1].plot([-spread, spread], [-spread, spread], "k", lw=0.8)
    axes[1].set(
        xlabel="V / V0 - 1, morphed mesh",
        ylabel="V / V0 - 1, surrogate",
        title="held-out μ, every cell (morph in the loop)",
    )
    for axis in axes:
        axis.grid(alpha=0.3)
    figure.tight_layout()
    with atomic_output(path) as temporary:
        figure.savefig(temporary, dpi=120)
    plt.close(figure)


if __name__ == "__main__":
    main()
