"""``inverse.models.predict_file`` gives the errors `phisim predict` gives, in the same words."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from inverse.models import predict_file
from phisim.errors import FileFormatError


@pytest.fixture
def files(tmp_path):
    data = tmp_path / "later.h5"
    with h5py.File(data, "w") as f:
        f["t0_fields/u"] = np.zeros((2, 8), dtype=np.float32)
        f["scalars/nu"] = np.float32(0.1)
    model = tmp_path / "run.adam.model.pt"
    model.write_bytes(b"PK\x03\x04 not a real archive")
    return model, data


def test_swapped_arguments_name_the_order(files, tmp_path):
    model, data = files
    with pytest.raises(FileFormatError, match=r"HDF5 file, not a model file.*predict_file\(model, inputs, out\)"):
        predict_file(data, model, tmp_path / "p.h5")


def test_an_unknown_key_lists_the_datasets(files, tmp_path):
    model, data = files
    with pytest.raises(FileFormatError, match=r"no dataset 'input'; its datasets: .*t0_fields/u"):
        predict_file(model, data, tmp_path / "p.h5", key="input")


def test_missing_and_folder_inputs(files, tmp_path):
    model, _ = files
    with pytest.raises(FileFormatError, match="does not exist"):
        predict_file(model, tmp_path / "nope.h5", tmp_path / "p.h5")
    with pytest.raises(FileFormatError, match="folder"):
        predict_file(model, tmp_path, tmp_path / "p.h5")
