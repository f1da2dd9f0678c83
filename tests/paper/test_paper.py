"""The paper's test cases as data (torchmorph.paper): families, regions, tables."""

from __future__ import annotations

import dataclasses
import json
import math
import sys

import numpy as np
import pytest
import torch
from conftest import structured_cube

from torchmorph.morph import MeshMorph
from torchmorph.paper import (
    CASES,
    HULL_CENTRE,
    CaseResult,
    MethodResult,
    PaperMesh,
    get_case,
    hull_rotation,
    load_mesh,
    plane_section,
    wing_bending,
)
from torchmorph.selection import SelectionPlan


def random_points(count: int = 50, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(count, 3, generator=generator, dtype=torch.float64) * 4.0 - 1.0


# ------------------------------------------------------------------------------ cases


def test_case_keys_and_aliases():
    assert list(CASES) == ["wing", "fluid-wing", "hull"]
    assert [spec.letter for spec in CASES.values()] == ["A", "B", "C"]
    assert get_case("A") is CASES["wing"]
    assert get_case("b") is CASES["fluid-wing"]
    assert get_case("fluid_wing") is CASES["fluid-wing"]
    assert get_case(" Hull ") is CASES["hull"]
    assert get_case(CASES["hull"]) is CASES["hull"]


def test_unknown_case_names_the_known_ones():
    with pytest.raises(ValueError, match="unknown case 'boat'; known: wing, fluid-wing, hull"):
        get_case("boat")


def test_mesh_cases_are_data_gen_names():
    assert [spec.mesh_case for spec in CASES.values()] == ["wing", "fluid_wing", "hull"]


def test_parameters_of_the_paper():
    wing, fluid, hull = CASES.values()
    assert (wing.domain, wing.mu_star, wing.n_train) == ((0.0, 1.3), 0.01, 100)
    assert (fluid.domain, fluid.mu_star, fluid.n_train) == ((0.0, 0.05), 0.01, 20)
    assert (hull.domain, hull.mu_star, hull.n_train) == ((-36.0, 0.0), -5.0, 50)
    for spec in CASES.values():
        assert (spec.a, spec.b) == (0.8, 1.3)
        assert spec.domain[0] <= spec.mu_star <= spec.domain[1]
    assert [spec.run_sidw for spec in CASES.values()] == [True, False, False]
    assert wing.moving == ("wing",) and fluid.moving == ("wing",) and hull.moving == ("hull",)


def test_wing_regions():
    radii = {region.names: region.radius for region in CASES["wing"].regions()}
    assert radii == {("root",): 0.05, ("tip",): 0.05, ("upper",): 0.5, ("lower",): 0.5}
    assert set(CASES["wing"].enrich) == {
        "root_profile",
        "tip_profile",
        "leading_edge",
        "trailing_edge",
    }


def test_fluid_wing_regions():
    radii = {region.names[0]: region.radius for region in CASES["fluid-wing"].regions()}
    assert radii == {
        "wall_x0": 0.5,
        "wall_x1": 0.5,
        "wall_y0": 0.5,
        "wall_y1": 0.5,
        "wall_z0": 0.25,
        "wall_z1": 0.25,
        "upper": 0.05,
        "lower": 0.05,
        "tip": 0.05,
    }
    # the sensitivity study of Fig. 10: box R, left/right walls 0.5 R, wing 0.1 R
    scaled = {region.names[0]: region.radius for region in CASES["fluid-wing"].regions(2.0)}
    assert scaled["wall_y1"] == 2.0 and scaled["wall_z0"] == 1.0
    assert scaled["upper"] == pytest.approx(0.2)


def test_hull_regions():
    # the paper configuration: walls and hull thinned alike (walls 2 m, hull 0.05 m)
    radii = {region.names[0]: region.radius for region in CASES["hull"].regions()}
    assert radii == pytest.approx(
        {
            "wall_x0": 2.0,
            "wall_x1": 2.0,
            "wall_y0": 2.0,
            "wall_y1": 2.0,
            "wall_z0": 2.0,
            "wall_z1": 2.0,
            "hull": 0.05,
        }
    )
    assert CASES["hull"].radius == 1.5 and CASES["hull"].variant == "paper"
    assert CASES["hull"].enrich == ("hull_edges",)
    # R = 1.5 m everywhere, as printed, is the documented variant "uniform"
    uniform = get_case("hull", "uniform")
    assert uniform.variant == "uniform" and uniform.enrich == ("hull_edges",)
    assert {region.radius for region in uniform.regions()} == {1.5}


def test_variants_and_their_errors():
    assert get_case("C", "paper") is CASES["hull"]
    assert get_case("wing", "paper") is CASES["wing"]
    with pytest.raises(
        ValueError,
        match="variant \\(case 'wing'\\) must be one of 'paper', 'adaptive'; got 'uniform'",
    ):
        get_case("wing", "uniform")
    with pytest.raises(ValueError, match="variant must be None for a CaseSpec"):
        get_case(CASES["hull"], "uniform")


def test_one_table_of_case_names():
    from data_gen.cases import CASE_ALIASES, canonical_case

    for spelling in ("fluid-wing", "fluid_wing", "FluidWing", " b ", "B"):
        assert canonical_case(spelling) == "fluid_wing"
        assert get_case(spelling) is CASES["fluid-wing"]
    assert CASE_ALIASES["c"] == "hull"
    for key, spec in CASES.items():
        assert canonical_case(key) == spec.mesh_case
        assert get_case(spec.letter) is spec


def test_plan_with_and_without_enrichment():
    spec = CASES["wing"]
    sidw, esidw = spec.plan(enrich=False), spec.plan()
    assert isinstance(esidw, SelectionPlan)
    assert sidw.enrich == () and esidw.enrich == spec.enrich
    assert esidw.overlap == "first"
    assert [region.radius for region in esidw.regions] == sorted(
        region.radius for region in esidw.regions
    )
    custom = spec.plan(0.1, a=0.5, b=2.0)
    assert {(region.a, region.b) for region in custom.regions} == {(0.5, 2.0)}
    assert max(region.radius for region in custom.regions) == pytest.approx(1.0)


def test_training_parameters_are_seeded_and_in_the_domain():
    for spec in CASES.values():
        first = spec.training_parameters(3)
        assert first.shape == (spec.n_train,) and first.dtype == torch.float64
        assert bool((first >= spec.domain[0]).all()) and bool((first <= spec.domain[1]).all())
        assert torch.equal(first, spec.training_parameters(3))
        assert not torch.equal(first, spec.training_parameters(4))


# ------------------------------------------------------------------------- families


def test_wing_bending_is_mu_z_squared():
    points = random_points()
    mu = torch.tensor([0.0, 0.01, 1.3], dtype=torch.float64)
    displacement = wing_bending(points, mu)
    assert displacement.shape == (3, 50, 3)
    expected = mu[:, None] * points[:, 2] ** 2
    assert torch.equal(displacement[..., 1], expected)
    assert torch.equal(displacement[..., 0], torch.zeros_like(expected))
    assert torch.equal(displacement[..., 2], torch.zeros_like(expected))
    single = wing_bending(points, 0.01)
    assert single.shape == (50, 3)
    torch.testing.assert_close(single, displacement[1], rtol=0, atol=0)


def test_wing_bending_is_differentiable_in_mu():
    points = random_points()
    mu = torch.tensor([0.3], dtype=torch.float64, requires_grad=True)
    (gradient,) = torch.autograd.grad(wing_bending(points, mu).sum(), mu)
    torch.testing.assert_close(gradient, (points[:, 2] ** 2).sum().reshape(1))


def test_hull_rotation_is_rigid():
    points = random_points(40)
    angles = torch.tensor([-36.0, -5.0, 0.0, 17.0], dtype=torch.float64)
    displacement = hull_rotation(points, angles)
    assert displacement.shape == (4, 40, 3)
    moved = points + displacement
    torch.testing.assert_close(
        torch.cdist(moved, moved, compute_mode="donot_use_mm_for_euclid_dist"),
        torch.cdist(points, points, compute_mode="donot_use_mm_for_euclid_dist").expand(4, -1, -1),
        rtol=0,
        atol=1e-12,
    )
    assert torch.equal(displacement[..., 2], torch.zeros(4, 40, dtype=torch.float64))
    assert torch.equal(displacement[2], torch.zeros(40, 3, dtype=torch.float64))


def test_hull_rotation_angle_and_sense():
    points = torch.tensor([[1.0, 0.0, 0.3], [0.0, 2.0, -1.0]], dtype=torch.float64)
    displacement = hull_rotation(points, 90.0)
    torch.testing.assert_close(
        points + displacement,
        torch.tensor([[0.0, 1.0, 0.3], [-2.0, 0.0, -1.0]], dtype=torch.float64),
        rtol=0,
        atol=1e-15,
    )
    # the paper's -5 degrees turns the bow (x > 0) down
    bow = hull_rotation(torch.tensor([[1.25, 0.0, 0.0]], dtype=torch.float64), -5.0)
    assert float(bow[0, 1]) == pytest.approx(1.25 * math.sin(math.radians(-5.0)))


def test_hull_rotation_keeps_its_centre():
    centre = torch.tensor([HULL_CENTRE], dtype=torch.float64)
    assert torch.equal(hull_rotation(centre, -20.0), torch.zeros(1, 3, dtype=torch.float64))
    shifted = hull_rotation(
        torch.tensor([[2.0, 1.0, 0.0]], dtype=torch.float64), 45.0, centre=(2.0, 1.0, 5.0)
    )
    assert torch.equal(shifted, torch.zeros(1, 3, dtype=torch.float64))


def test_family_moves_only_the_moving_sets():
    mesh = structured_cube(3)
    morph = MeshMorph(mesh)
    spec = dataclasses.replace(CASES["wing"], moving=("x1",))
    family = spec.family(morph)
    mu = torch.tensor([0.5, 2.0], dtype=torch.float64)
    boundary = family(mu)
    assert boundary.shape == (2, morph.num_boundary, 3)
    moving = morph.boundary_mask("x1")
    z = morph.boundary_points[:, 2]
    torch.testing.assert_close(boundary[:, moving, 1], mu[:, None] * z[moving] ** 2, rtol=0, atol=0)
    assert not bool(boundary[:, ~moving].any())
    assert family(0.5).shape == (morph.num_boundary, 3)
    # the whole mesh follows: boundary exact, interior interpolated
    field = morph(boundary)
    assert field.shape == (2, mesh.num_nodes, 3)


def test_family_rejects_matrix_parameters():
    with pytest.raises(ValueError, match="mu must be a scalar or of shape"):
        wing_bending(random_points(), torch.zeros(2, 2, dtype=torch.float64))


# --------------------------------------------------------------------------- tables


def test_paper_meshes():
    expected = {
        "wing": (8850, 2463, 797, 1666),
        "fluid-wing": (169598, 36036, 21910, 14126),
        "hull": (30265, 7186, 3322, 3864),
    }
    for key, spec in CASES.items():
        mesh = spec.paper_mesh
        assert (mesh.tets, mesh.nodes, mesh.interior, mesh.boundary) == expected[key]
        assert mesh.interior + mesh.boundary == mesh.nodes
    assert (CASES["fluid-wing"].paper_mesh.max_q, CASES["fluid-wing"].paper_mesh.mean_q) == (
        4.31,
        1.48,
    )
    hull = CASES["hull"].paper_mesh
    assert (hull.max_q, hull.mean_q, hull.max_q_deformed, hull.mean_q_deformed) == (
        2.47,
        1.62,
        2.56,
        1.63,
    )


def test_paper_tables_are_complete():
    methods = {key: [row.method for row in spec.paper_rows] for key, spec in CASES.items()}
    assert methods["wing"] == ["IDW", "SIDW", "ESIDW", "POD-IDW", "POD-ESIDW"]
    assert methods["fluid-wing"] == ["IDW", "ESIDW", "POD-IDW", "POD-ESIDW"]
    assert methods["hull"] == [
        "IDW",
        "ESIDW",
        "POD-IDW",
        "POD-IDW (1 mode)",
        "POD-IDW (2 modes)",
        "POD-ESIDW",
        "POD-ESIDW (1 mode)",
        "POD-ESIDW (2 modes)",
    ]
    for spec in CASES.values():
        assert [spec.mesh_table, spec.results_table] in ([1, 4], [2, 5], [3, 6])
        for row in spec.paper_rows:
            assert row.online_s > 0 and row.controls > 0 and row.error
            is_pod = row.method.startswith("POD")
            assert (row.offline_s is not None) == is_pod
            assert (row.modes is not None) == is_pod
            assert (row.error_value is None) == (row.method == "IDW")
            if row.method.endswith("IDW") and not row.method.endswith("SIDW"):
                assert row.controls == spec.paper_mesh.boundary


def test_paper_table_values():
    wing, fluid, hull = CASES.values()
    row = wing.paper_row("ESIDW")
    assert (row.controls, row.online_s, row.error, row.error_value) == (
        390,
        0.034,
        "1.06 %",
        0.0106,
    )
    assert wing.paper_row("SIDW").controls == 92
    assert wing.paper_row("POD-IDW").offline_s == 90.93
    assert fluid.paper_row("IDW").online_s == 83.09
    assert fluid.paper_row("POD-ESIDW").offline_s == 1613.65
    assert fluid.paper_row("ESIDW").controls == 9339
    assert hull.paper_row("ESIDW").error == "2.42 %"
    assert hull.paper_row("POD-IDW (1 mode)").error == "0.23–2.85 %"
    assert hull.paper_row("POD-ESIDW").modes == 2
    assert hull.paper_row("nonsense") is None


# -------------------------------------------------------------------------- helpers


def test_plane_section_of_a_cube_has_its_area():
    mesh = structured_cube(4, size=2.0)
    # y = 1.0 runs through a layer of nodes: they count as lying above the plane
    for axis, value in ((0, 0.7), (1, 1.0), (2, 1.9)):
        _, first, second, weight = plane_section(mesh.points, mesh.tets, axis, value)
        points = mesh.points.numpy()
        vertices = (1 - weight)[..., None] * points[first] + weight[..., None] * points[second]
        assert np.allclose(vertices[..., axis], value)
        plane = [i for i in range(3) if i != axis]
        x, y = vertices[..., plane[0]], vertices[..., plane[1]]
        area = 0.5 * np.abs((x * np.roll(y, -1, 1) - np.roll(x, -1, 1) * y).sum(1))
        assert area.sum() == pytest.approx(4.0, rel=1e-12)
        assert (area >= 0).all()
        if value != 1.0:
            assert (area > 0).all()


def test_case_result_report_and_lookup():
    spec = CASES["wing"]
    rows = [
        MethodResult("IDW", 10, 0.01, None, 0, 2.0, 1.5, assembly_s=0.1),
        MethodResult(
            "ESIDW",
            4,
            0.002,
            0.0123,
            0,
            2.1,
            1.5,
            selection_s=0.01,
            assembly_s=0.05,
            error_nodal=0.02,
        ),
    ]
    quality = {"max_edge_ratio": 2.0, "mean_edge_ratio": 1.5, "num_inverted": 0}
    result = CaseResult(
        case="wing",
        letter="A",
        title=spec.title,
        size="small",
        mesher="gmsh",
        seed=0,
        mu_star=0.01,
        mesh={"tets": 5, "nodes": 14, "interior": 4, "boundary": 10, "max_q": 2.0, "mean_q": 1.5},
        paper_mesh=spec.paper_mesh,
        rows=rows,
        paper_rows=spec.paper_rows,
        quality_reference=quality,
        quality_deformed={"IDW": quality},
        singular_values={},
        mesh_table=1,
        results_table=4,
    )
    text = result.report()
    assert "Table 1" in text and "Table 4" in text and "1.23 %" in text and "1.06 %" in text
    assert result.row("ESIDW").controls == 4
    with pytest.raises(KeyError, match="known: IDW, ESIDW"):
        result.row("SIDW")
    markdown = result.result_lines(markdown=True)
    assert markdown[0].startswith("| method |") and len(markdown) == 4
    assert result.to_dict()["paper_mesh"]["tets"] == 8850
    assert isinstance(result.paper_mesh, PaperMesh)
    again = CaseResult.from_dict(json.loads(json.dumps(result.to_dict())))
    assert again == result


def test_load_mesh_without_data_gen_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "data_gen", None)
    with pytest.raises(ImportError, match=r"torchmorph\[mesh\]"):
        load_mesh("wing", size="small")


@pytest.mark.slow  # a fresh interpreter importing torch: seconds
def test_core_never_imports_the_reproduction():
    import subprocess

    code = (
        "import sys, torchmorph, torchmorph.idw, torchmorph.selection, torchmorph.morph, "
        "torchmorph.pod, torchmorph.mesh, torchmorph.mesh.quality, torchmorph.mesh.io\n"
        "bad = sorted(m for m in sys.modules "
        "if m.startswith(('data_gen', 'torchmorph.paper')))\n"
        "print(bad)\nsys.exit(1 if bad else 0)"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=120
    )
    assert run.returncode == 0, run.stdout + run.stderr
