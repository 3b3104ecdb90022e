"""``flyscan bench stripe`` in its quick form: the figures it writes, among them."""
import json

from benchmarks import stripe as bench
from benchmarks.stripe.scenes import SCENES, TARGET_MEASURED

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_writes_the_scenes_and_the_cell_frames(tmp_path):
    result = bench.run(tmp_path, quick=True)
    saved = json.loads((tmp_path / "stripe.json").read_text())
    assert saved["summary"] == json.loads(json.dumps(result["summary"]))
    for name in ("stripe.png", "stripe_scenes.png"):
        assert (tmp_path / name).read_bytes()[:8] == PNG_MAGIC
    scenes = saved["photographed_lines"]
    assert set(scenes) == set(SCENES)
    for name, figures in scenes.items():
        for key in ("fixed_20dn", "auto"):
            f = figures[key]
            assert f["columns_with_stripe"] > 300  # one 640-column frame per scene (quick)
            if figures["held_to_target"]:  # >= 99 % measured, none false
                assert f["measured_fraction"] >= TARGET_MEASURED, (name, key, f)
                assert f["false_columns"] == 0, (name, key, f)
    assert saved["summary"]["photographed_lines"]["met"]
    cell = saved["cell_frames"]
    assert cell["frames"] >= 20  # the demo block's pass: frames holding a stripe
    assert cell["stripe_ms"] > 0 and cell["copy_ms"] > 0
