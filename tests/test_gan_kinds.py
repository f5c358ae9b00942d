"""The table of GAN kinds: every kind is offered, recognised, and explained when its checkpoint is missing."""
import subprocess
import sys

import pytest

from datagen.errors import UserError
from datagen.gans.checkpoint import CheckpointError, detect_kind, read_checkpoint
from datagen.gans.kinds import GAN_KINDS, KINDS
from datagen.gans.triplane import PLANE_SAMPLERS
from datagen.generators import AVAILABLE, GANS, make_generator
from tests.conftest import gan_fixture


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_is_offered_and_has_a_sampler(kind):
    assert kind in AVAILABLE and kind in GANS
    assert GAN_KINDS[kind].layout in PLANE_SAMPLERS


@pytest.mark.parametrize("kind", KINDS)
def test_a_missing_checkpoint_names_where_they_come_from(kind, tmp_path):
    source = GAN_KINDS[kind].source
    with pytest.raises(UserError) as no_path:
        make_generator(kind)
    with pytest.raises(CheckpointError) as no_file:
        read_checkpoint(tmp_path / "absent.pkl", kind)
    assert source in str(no_path.value) and source in str(no_file.value)


@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_recognises_its_checkpoint(kind):
    assert read_checkpoint(gan_fixture(kind, ".pkl")).kind == kind


def test_a_checkpoint_is_the_last_kind_that_recognises_it():
    assert detect_kind({"decoder.net.0.weight": None}, {}) == "eg3d"
    assert detect_kind({"t_mapping.fc0.weight": None}, {}) == "panohead"
    assert detect_kind({}, {"triplane_depth": 3}) == "panohead"
    assert detect_kind({"ConvA.0.weight": None, "t_mapping.fc0.weight": None}, {"triplane_depth": 3}) == "spherehead"


def test_the_command_line_lists_the_kinds_without_torch():
    code = "import sys, datagen.cli; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
