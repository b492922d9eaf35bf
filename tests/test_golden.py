"""The golden outputs (`tests/golden/record.py`): small lattices (irradiance, SH, split SH,
ambient occlusion, a point light, a Dask cluster bake, a relit lazy bake) and pictures of
every shading mode are identical to the bit to the recorded ones. Code that is moved or
reshaped without meaning to change a result must leave them so; a change that means to
change results re-records them (``python tests/golden/record.py``) and says why."""

import json

import pytest
from golden.record import HASHES, differences, record


@pytest.mark.slow
def test_lattices_and_pictures_are_identical_to_the_recorded_ones():
    pytest.importorskip("distributed")
    want = json.loads(HASHES.read_text())
    got = record()
    assert not differences(want, got), differences(want, got)
