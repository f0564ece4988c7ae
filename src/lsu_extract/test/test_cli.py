"""`lsu extract` on image files: summary, JSON, overlay, errors."""

import json

import cv2
import numpy as np
import pytest

from lsu_extract.cli import main
from lsu_extract.extractor import DEFAULT_METHOD
from lsu_extract.synthetic import LineScene, render_line


@pytest.fixture
def line_png(tmp_path):
    image, truth, _ = render_line(LineScene(textured=False, height=96, seed=3))
    path = tmp_path / "snap.png"
    cv2.imwrite(str(path), image)
    return path, truth


def test_json_output_has_one_centre_per_row(line_png, capsys):
    path, truth = line_png
    assert main([str(path), "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["rows_detected"] == 96 and record["method"] == DEFAULT_METHOD
    u, v = np.array(record["u"]), np.array(record["v"]).astype(int)
    assert np.max(np.abs(u - truth[v])) < 0.2


def test_overlay_marks_the_line(line_png, tmp_path, capsys):
    path, truth = line_png
    out = tmp_path / "overlay.png"
    assert main([str(path), "--method", "thesis", "--overlay", str(out)]) == 0
    assert "96/96 rows, method thesis" in capsys.readouterr().out
    overlay = cv2.imread(str(out)).astype(int)
    dimmed = (cv2.imread(str(path)).astype(np.float32) * 0.6).astype(int)
    row = 50
    marked = np.nonzero(np.abs(overlay[row] - dimmed[row]).sum(axis=1) > 30)[0]  # where dots were drawn
    assert marked.size > 0 and np.all(np.abs(marked - truth[row]) <= 2.5)


def test_missing_file_is_a_plain_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        main([str(tmp_path / "nope.png")])
    bad = tmp_path / "bad.png"
    bad.write_text("not an image")
    with pytest.raises(ValueError, match="not an image OpenCV can read"):
        main([str(bad)])


@pytest.mark.slow
def test_lsu_extract_subcommand_is_registered(line_png, lsu_cli):
    path, _ = line_png
    result = lsu_cli("extract", str(path), "--method", "gaussian3", timeout=60)
    assert result.returncode == 0, result.stderr
    assert "96/96 rows, method gaussian3" in result.stdout
    missing = lsu_cli("extract", str(path) + ".missing", timeout=60)
    assert missing.returncode == 2 and "not found" in missing.stderr and "Traceback" not in missing.stderr


def test_explain_says_which_model_centred_each_row_and_why(tmp_path, capsys):
    # the top half clips (red at 255, crosstalk in green and blue), the bottom half is a plain 4 px line
    clipped, _, _ = render_line(LineScene(amplitude_dn=420.0, leak_green=0.10, leak_blue=0.08, fwhm_px=7.0, height=96))
    plain, _, _ = render_line(LineScene(textured=False, height=96, seed=3))
    path = tmp_path / "mixed.png"
    cv2.imwrite(str(path), np.concatenate([clipped[:48], plain[48:]]))
    assert main([str(path), "--json", "--explain"]) == 0
    record = json.loads(capsys.readouterr().out)
    model, v = record["model"], np.array(record["v"])
    assert len(model) == len(v) == record["rows_detected"]
    top = [m for m, row in zip(model, v) if row < 46]
    bottom = [m for m, row in zip(model, v) if row > 50]
    assert top.count("flanks_signal") >= 0.9 * len(top) and set(bottom) == {"blais_rioux4"}
    assert record["models"]["flanks_signal"]["rows"] == model.count("flanks_signal")
    assert "clipped" in record["models"]["flanks_signal"]["why"]
    assert main([str(path), "--explain"]) == 0
    text = capsys.readouterr().out
    assert "rows flanks_signal: red clipped" in text and "rows blais_rioux4: FWHM <= 5" in text
