"""FitSettings' record (to_dict / from_dict): what a material file and a checkpoint keep of
the settings a fit ran at, read back as the settings themselves."""
from __future__ import annotations

import json

from pd_tool.fit.settings import FitSettings


def test_the_record_survives_json_and_reads_back_as_the_same_settings() -> None:
    s = FitSettings(quality="draft", background=(0.2, 0.3, 0.4), rounds=2, residual_pool=0.5).resolved()
    record = json.loads(json.dumps(s.to_dict()))
    assert record["background"] == [0.2, 0.3, 0.4]  # a tuple is written as JSON's list
    back = FitSettings.from_dict(record)
    assert back == s and isinstance(back.background, tuple)


def test_a_record_from_another_version_keeps_what_it_can() -> None:
    record = FitSettings(quality="final", lr_residual=0.05).to_dict()
    record["a_setting_this_version_lacks"] = 3
    del record["residual_decay"]
    back = FitSettings.from_dict(record)
    assert back.quality == "final" and back.lr_residual == 0.05
    assert back.residual_decay == FitSettings().residual_decay
