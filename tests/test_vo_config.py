"""The documented configuration file and the TOML loader."""

from pathlib import Path

import pytest

from granite.errors import ConfigError
from granite.estimator.config import VoConfig

DEFAULT_FILE = Path(__file__).resolve().parents[1] / "configs" / "mono_default.toml"


def test_documented_file_lists_exactly_the_defaults():
    import tomllib

    data = tomllib.loads(DEFAULT_FILE.read_text())
    assert VoConfig.load(DEFAULT_FILE) == VoConfig()
    written = tomllib.loads(VoConfig().to_toml())
    assert {k: set(v) for k, v in data.items()} == {k: set(v) for k, v in written.items()}


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[optical_flow]\nlevelz = 3\n", "levelz"),
        ("[nonsense]\n", "nonsense"),
        ("[backend]\nobs_std_dev = -1\n", "obs_std_dev"),
        ("[estimator]\nkeyframe_entropy_fraction = 2.0\n", "keyframe_entropy_fraction"),
        ("not toml = = 1", "TOML"),
    ],
)
def test_bad_configuration_is_one_clear_error(tmp_path, text, fragment):
    path = tmp_path / "c.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        VoConfig.load(path)
    assert fragment in str(info.value) and str(path) in str(info.value)
