"""Point lights, OLAT rigs from lights.arrow tables, directional lights."""

from __future__ import annotations

import json

import pyarrow as pa
import pytest
import torch

from relightanyone.render.lights import (
    DirectionalLights,
    PointLights,
    fibonacci_sphere_directions,
    olat_rig_from_table,
    stack_padded,
)


def _lights_table(positions, intensities, index):
    vector = pa.list_(pa.float64(), 3)
    return pa.table(
        {
            "index": pa.array(index, pa.int32()),
            "position_m": pa.array(positions, vector),
            "intensity_rgb": pa.array(intensities, vector),
        }
    )


def test_olat_rig_from_arrow_table_follows_the_index_column():
    table = _lights_table(
        positions=[[0.0, 0.0, 2.0], [1.0, 0.0, 0.0], [0.0, 1.5, 0.0]],
        intensities=[[3.0, 3.0, 3.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]],
        index=[2, 0, 1],
    )
    rig = olat_rig_from_table(table)
    assert len(rig) == 3 and rig.positions.dtype == torch.float32
    assert rig.positions.tolist() == [[1.0, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 0.0, 2.0]]
    assert rig.intensities[:, 0].tolist() == [1.0, 2.0, 3.0]
    olat = rig.olat(2)
    assert len(olat) == 1 and olat.positions.tolist() == [[0.0, 0.0, 2.0]]
    assert rig.full_on() is rig
    assert rig.select([1, 0]).intensities[:, 0].tolist() == [2.0, 1.0]
    with pytest.raises(IndexError, match="out of range"):
        rig.olat(3)


def test_olat_rig_from_column_mapping_and_real_faceolat_positions(real_fixtures):
    metadata = json.loads((real_fixtures / "faceolat" / "light_pattern_metadata.json").read_text())
    positions_m = [[value / 1000.0 for value in position] for position in metadata["light_positions"]]
    rig = olat_rig_from_table(
        {"position_m": positions_m, "intensity_rgb": [[1.0, 1.0, 1.0]] * len(positions_m)}
    )
    assert len(rig) == 331
    centre = rig.positions.mean(0)
    radii = (rig.positions - centre).norm(dim=-1)
    assert radii.max() < 3.5 and radii.min() > 0.1  # a dome of lights around the subject, in metres


def test_olat_rig_errors_name_the_problem():
    with pytest.raises(ValueError, match="lights.arrow: missing column 'intensity_rgb'"):
        olat_rig_from_table({"position_m": [[0, 0, 1]]}, source="lights.arrow")
    with pytest.raises(ValueError, match="'position_m' must hold 3 numbers per row"):
        olat_rig_from_table({"position_m": [[0, 0]], "intensity_rgb": [[1, 1, 1]]})
    with pytest.raises(ValueError, match="'index' must be a permutation"):
        olat_rig_from_table(
            {"position_m": [[0, 0, 1]] * 2, "intensity_rgb": [[1, 1, 1]] * 2, "index": [0, 0]}
        )
    with pytest.raises(ValueError, match="negative"):
        olat_rig_from_table({"position_m": [[0, 0, 1]], "intensity_rgb": [[-1, 1, 1]]})
    with pytest.raises(ValueError, match="intensities"):
        PointLights(torch.zeros(2, 3), torch.zeros(3, 3))


def test_transform_scale_and_padding():
    lights = PointLights(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([[1.0, 2.0, 3.0]]))
    shift = torch.eye(4)
    shift[:3, 3] = torch.tensor([0.0, 1.0, 0.0])
    moved = lights.transformed(shift)
    assert moved.positions.tolist() == [[0.0, 1.0, 1.0]]
    assert lights.scaled(2.0).intensities.tolist() == [[2.0, 4.0, 6.0]]
    other = PointLights(torch.ones(3, 3), torch.ones(3, 3))
    positions, intensities, counts = stack_padded([lights, other])
    assert positions.shape == (2, 3, 3) and counts.tolist() == [1, 3]
    assert (intensities[0, 1:] == 0).all()


def test_directional_lights_as_point_lights_keep_the_irradiance():
    dirs = fibonacci_sphere_directions(50)
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(50))
    assert dirs.mean(0).abs().max() < 0.05  # nearly uniform
    lights = DirectionalLights(dirs, torch.full((50, 3), 0.5))
    points = lights.as_point_lights(10.0)
    irradiance_at_origin = points.intensities / points.positions.norm(dim=-1, keepdim=True) ** 2
    torch.testing.assert_close(irradiance_at_origin, lights.irradiance)
