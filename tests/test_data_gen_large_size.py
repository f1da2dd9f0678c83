"""The ``large`` data_gen size (about 10^6 nodes): accepted, sane, never meshed here."""

from __future__ import annotations

import pytest

from data_gen import cases


@pytest.mark.parametrize("case", ["fluid_wing", "hull"])
def test_large_size_is_accepted_and_finer_than_paper(case, tmp_path):
    assert "large" in cases.SIZES
    path = cases.cache_path(case, "large", cache_dir=tmp_path)
    assert path.name.startswith(f"{case}-large-gmsh-") and not path.exists()
    large = cases.PARAMETERS[case]["gmsh"]["large"]
    paper = cases.PARAMETERS[case]["gmsh"]["paper"]
    assert large is cases.LARGE_PARAMETERS[case]
    assert set(large) == set(paper)
    sizes = [key for key in large if key.startswith("h_")]
    assert sizes
    # every mesh size at least 3x finer: >= 27x the paper's nodes in the volume
    for key in sizes:
        assert 0 < large[key] <= paper[key] / 3, key
    assert large["h_min"] < large["h_body"] < large["h_far"]
    assert large["optimize"] == ""  # Netgen's optimiser would take longer than meshing
    # distinct cache entries for distinct sizes
    assert path != cases.cache_path(case, "paper", cache_dir=tmp_path)


@pytest.mark.parametrize(("case", "mesher"), [("wing", "gmsh"), ("hull", "pytetwild")])
def test_large_size_only_where_defined(case, mesher, tmp_path):
    with pytest.raises(
        ValueError,
        match=f"size 'large' is not defined for case '{case}' "
        f"with mesher '{mesher}'; its sizes: small, paper",
    ):
        cases.cache_path(case, "large", mesher, cache_dir=tmp_path)
