import json

import pytest
from numpy.testing import assert_allclose

from ipmc_model.errors import ModelFileError, NotFittedError
from ipmc_model.lssvm import FixedSizeLSSVMRegressor, LSSVMRegressor
from ipmc_model.narx import InverseNarxModel, NarxCommittee, NarxModel
from ipmc_model.persistence import (
    DOCUMENT_CHECKSUM,
    FORMAT_VERSION,
    check_model_output,
    document_sha256,
    load_model,
    save_model,
)
from ipmc_model.play import PrandtlIshlinskii


def _rewrite(path, doc):
    """Write ``doc`` as the model file ``path`` with a matching document checksum, as a writer
    would: the loader's checks of the content itself are what is tested then."""
    doc[DOCUMENT_CHECKSUM] = document_sha256(doc)
    path.write_text(json.dumps(doc))


def _as_old_version(path, version):
    """Make ``path`` a file as written before the document checksum (format ``version``)."""
    doc = json.loads(path.read_text())
    doc["format_version"] = version
    del doc[DOCUMENT_CHECKSUM]
    path.write_text(json.dumps(doc, indent=2))
    return doc


@pytest.fixture(scope="module")
def models(hyst_data):
    u, y = hyst_data
    u, y = u[:500], y[:500]
    return {
        "pi": PrandtlIshlinskii(n_operators=5).fit(u, y),
        "narx": NarxModel(LSSVMRegressor(C=100.0, sigma=2.0), lag_step=2).fit(u, y),
        "narx-fs": NarxModel(FixedSizeLSSVMRegressor(C=100.0, sigma=2.0, n_prototypes=50))
        .fit(u, y),
        "inverse": InverseNarxModel(LSSVMRegressor(C=100.0, sigma=2.0)).fit(u, y),
        "inverse-memory": InverseNarxModel(LSSVMRegressor(C=100.0, sigma=2.0), input_lags=0,
                                           memory_taus_s=[0.5, 3.0], dt_s=0.02).fit(u, y),
    }


@pytest.mark.parametrize("name", ["pi", "narx", "narx-fs", "inverse", "inverse-memory"])
def test_save_load_round_trip(tmp_path, hyst_data, models, name):
    u, y = hyst_data
    model = models[name]
    path = save_model(model, tmp_path / "m", metadata={"note": "test"})
    assert path.suffix == ".json" and path.with_suffix(".npz").exists()
    loaded = load_model(path)
    assert type(loaded) is type(model)
    assert loaded.metadata_ == {"note": "test"}
    if name == "pi":
        assert_allclose(loaded.simulate(u[500:]), model.simulate(u[500:]))
    elif name.startswith("inverse"):
        assert loaded.get_params() == model.get_params()
        assert_allclose(loaded.simulate(y[500:600]), model.simulate(y[500:600]))
    else:
        assert_allclose(loaded.simulate(u[500:600]), model.simulate(u[500:600]))
        assert_allclose(loaded.predict(u[500:600], y[500:600]),
                        model.predict(u[500:600], y[500:600]))


def test_load_missing_file(tmp_path):
    with pytest.raises(ModelFileError, match=r"no such model file\.$"):
        load_model(tmp_path / "nope.json")


def test_load_corrupt_json(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text("{ not json")
    with pytest.raises(ModelFileError, match="not valid JSON"):
        load_model(p)


def test_load_foreign_json(tmp_path):
    p = tmp_path / "foreign.json"
    p.write_text(json.dumps({"name": "something else"}))
    with pytest.raises(ModelFileError, match="not an ipmc-ros model file"):
        load_model(p)


def test_load_binary_garbage(tmp_path):
    p = tmp_path / "garbage.json"
    p.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe")
    with pytest.raises(ModelFileError) as info:
        load_model(p)
    assert str(info.value).count(".") >= 1 and "\n" not in str(info.value)


def test_load_newer_version(tmp_path, models):
    path = save_model(models["pi"], tmp_path / "m.json")
    doc = json.loads(path.read_text())
    doc["format_version"] = FORMAT_VERSION + 1
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match="newer than this ipmc_model supports"):
        load_model(path)


def test_load_tampered_arrays(tmp_path, models):
    path = save_model(models["narx"], tmp_path / "m.json")
    npz = path.with_suffix(".npz")
    npz.write_bytes(npz.read_bytes()[:-10])
    with pytest.raises(ModelFileError, match=r"arrays file m\.npz was changed or corrupted"):
        load_model(path)
    npz.unlink()
    with pytest.raises(ModelFileError, match="missing"):
        load_model(path)


def test_model_file_error_is_value_error():
    assert issubclass(ModelFileError, ValueError)


def test_save_unfitted_raises(tmp_path):
    with pytest.raises(NotFittedError):
        save_model(NarxModel(), tmp_path / "m.json")


def test_inverse_file_without_memory_keys_loads(tmp_path, hyst_data, models):
    # Files written before memory channels existed have no memory_taus_s / dt_s.
    u, y = hyst_data
    path = save_model(models["inverse"], tmp_path / "old")
    doc = _as_old_version(path, 1)
    for key in ("memory_taus_s", "dt_s"):
        del doc["model"]["params"][key]
    path.write_text(json.dumps(doc))
    loaded = load_model(path)
    assert loaded.memory_taus_s == ()
    assert_allclose(loaded.simulate(y[500:600]), models["inverse"].simulate(y[500:600]))


@pytest.fixture(scope="module")
def channel_model(hyst_data):
    u, y = hyst_data
    return NarxModel(LSSVMRegressor(C=100.0, sigma=2.0), input_lags=0, output_lags=0,
                     input_memory_taus_s=(0.3, 0.5), include_voltage=False,
                     dt_s=0.02).fit(u[:500], y[:500])


def test_voltage_channel_model_round_trip(tmp_path, hyst_data, channel_model):
    u, y = hyst_data
    path = save_model(channel_model, tmp_path / "fwd")
    doc = json.loads(path.read_text())
    assert doc["format_version"] == FORMAT_VERSION and doc["kind"] == "lssvm-narx"
    assert doc["model"]["params"]["input_memory_taus_s"] == [0.3, 0.5]
    assert doc["model"]["params"]["include_voltage"] is False
    assert doc["model"]["params"]["dt_s"] == 0.02
    loaded = load_model(path)
    assert loaded.uses_voltage_channels
    assert loaded.get_params() == channel_model.get_params()
    # The file alone rebuilds the channels from the raw voltage.
    assert_allclose(loaded.simulate(u[500:700]), channel_model.simulate(u[500:700]))
    assert_allclose(loaded.predict(u[500:700], y[500:700]),
                    channel_model.predict(u[500:700], y[500:700]))
    st = loaded.stepper()
    assert_allclose([st.step(v) for v in u[500:550]], channel_model.simulate(u[500:550]),
                    rtol=1e-9, atol=1e-12)


def test_model_without_voltage_channels_stores_no_channel_parameters(tmp_path, models):
    path = save_model(models["narx"], tmp_path / "plain")
    doc = json.loads(path.read_text())
    assert doc["format_version"] == FORMAT_VERSION
    assert not set(doc["model"]["params"]) & {"input_memory_taus_s", "include_voltage", "dt_s"}
    assert not load_model(path).uses_voltage_channels


def test_voltage_channel_file_with_wrong_channels_is_corrupt(tmp_path, channel_model):
    path = save_model(channel_model, tmp_path / "fwd")
    doc = json.loads(path.read_text())
    doc["model"]["params"]["input_memory_taus_s"] = [0.3]   # one channel, lags for two
    _rewrite(path, doc)
    with pytest.raises(ModelFileError, match="corrupt model content.*voltage channel"):
        load_model(path)
    doc["model"]["params"]["input_memory_taus_s"] = [0.3, -0.5]
    _rewrite(path, doc)
    with pytest.raises(ModelFileError, match="corrupt model content.*memory_taus_s"):
        load_model(path)
    doc["format_version"] = FORMAT_VERSION + 1
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match="newer than this ipmc_model supports"):
        load_model(path)


def test_committee_round_trip(tmp_path, hyst_data):
    u, y = hyst_data
    members = [NarxModel(LSSVMRegressor(C=100.0, sigma=2.0), input_lags=k, output_lags=0,
                         lag_step=2) for k in (3, 5)]
    model = NarxCommittee(members).fit(u[:500], y[:500])
    path = save_model(model, tmp_path / "committee")
    doc = json.loads(path.read_text())
    assert doc["format_version"] == FORMAT_VERSION and doc["kind"] == "lssvm-narx-committee"
    loaded = load_model(path)
    assert type(loaded) is NarxCommittee and loaded.max_lag_ == model.max_lag_ == 10
    assert_allclose(loaded.simulate(u[500:600]), model.simulate(u[500:600]))
    st = loaded.stepper()
    assert_allclose([st.step(v) for v in u[500:600]][10:], model.simulate(u[500:600])[10:],
                    rtol=1e-9, atol=1e-12)
    # a member whose regressor does not match its lags is a corrupt file, not a crash
    doc["model"]["members"][1]["input_lags_"] = [3]
    _rewrite(path, doc)
    with pytest.raises(ModelFileError, match="corrupt model content.*lags"):
        load_model(path)
    doc["model"]["members"] = doc["model"]["members"][:1]
    _rewrite(path, doc)
    with pytest.raises(ModelFileError, match="corrupt model content.*at least 2 members"):
        load_model(path)


CHANGED = r"m\.json: the model file was changed or corrupted after it was written"


@pytest.mark.parametrize("edit", ["intercept", "offset", "metadata", "kind", "arrays_sha256"])
def test_an_edited_number_or_field_in_the_json_is_refused(tmp_path, models, edit):
    name = "pi" if edit == "offset" else "narx"
    path = save_model(models[name], tmp_path / "m", metadata={"data": "day1.csv"})
    doc = json.loads(path.read_text())
    if edit == "intercept":
        doc["model"]["regressor"]["intercept"] = 1e6
    elif edit == "offset":
        doc["model"]["offset"] += 1.0
    elif edit == "metadata":
        doc["metadata"]["data"] = "day2.csv"
    elif edit == "kind":
        doc["kind"] = "lssvm-narx-inverse"
    else:  # the NPZ file's checksum edited to match an edited NPZ file
        doc["arrays_sha256"] = "0" * 64
    path.write_text(json.dumps(doc, indent=2))
    with pytest.raises(ModelFileError, match=CHANGED) as info:
        load_model(path)
    msg = str(info.value)
    assert "\n" not in msg and msg.endswith(".") and msg.count(". ") == 0


def test_a_lowered_version_or_a_missing_checksum_does_not_skip_the_check(tmp_path, models):
    path = save_model(models["pi"], tmp_path / "m")
    doc = json.loads(path.read_text())
    doc["model"]["offset"] = 1e6
    doc["format_version"] = 4  # the checksum present is checked whatever the version says
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match=CHANGED):
        load_model(path)
    doc["format_version"] = FORMAT_VERSION
    del doc[DOCUMENT_CHECKSUM]  # a current file always has one
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match=CHANGED):
        load_model(path)


def test_the_checksum_ignores_layout_but_not_values(tmp_path, hyst_data, models):
    u, _ = hyst_data
    path = save_model(models["pi"], tmp_path / "m")
    doc = json.loads(path.read_text())
    # re-indented, keys reordered: the same document
    path.write_text(json.dumps(dict(reversed(list(doc.items()))), indent=4, sort_keys=False))
    assert_allclose(load_model(path).simulate(u[:100]), models["pi"].simulate(u[:100]))


@pytest.mark.parametrize("version", [1, 4])
def test_files_of_earlier_versions_load_with_the_arrays_check(tmp_path, hyst_data, models,
                                                              version):
    u, _ = hyst_data
    path = save_model(models["pi"], tmp_path / "m")
    _as_old_version(path, version)
    assert_allclose(load_model(path).simulate(u[:100]), models["pi"].simulate(u[:100]))
    npz = path.with_suffix(".npz")
    npz.write_bytes(npz.read_bytes()[:-1] + b"x")
    with pytest.raises(ModelFileError, match="its arrays file m.npz was changed or corrupted"):
        load_model(path)


def test_a_failed_save_leaves_no_file_and_no_temporary(tmp_path, models):
    with pytest.raises(TypeError, match="not JSON serialisable"):
        save_model(models["pi"], tmp_path / "m", metadata={"when": object()})
    assert list(tmp_path.iterdir()) == []


def test_a_save_replaces_the_pair_whole(tmp_path, hyst_data, models):
    u, _ = hyst_data
    path = save_model(models["narx"], tmp_path / "m")
    path = save_model(models["pi"], tmp_path / "m")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "m.npz"]
    assert_allclose(load_model(path).simulate(u[:100]), models["pi"].simulate(u[:100]))


@pytest.mark.parametrize(("name", "match"), [
    ("folder", r"--out .*folder is a folder; give a model file name"),
    ("folder.json", r"--out .*folder\.json is a folder"),
    ("m.npz", r"--out .*m\.npz: a model file is a \.json name"),
    ("day1.csv", r"--out .*day1\.csv: a model file is a \.json name"),
    ("file/m.json", r"--out .*file/m\.json: .*file is a file, not a folder"),
    ("twin", r"--out .*twin\.npz is a folder"),
])
def test_check_model_output_refuses_what_cannot_be_written(tmp_path, name, match):
    (tmp_path / "folder").mkdir()
    (tmp_path / "folder.json").mkdir()
    (tmp_path / "twin.npz").mkdir()
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match=match):
        check_model_output(tmp_path / name)


def test_check_model_output_gives_the_json_path(tmp_path):
    assert check_model_output(tmp_path / "new" / "m") == tmp_path / "new" / "m.json"
    assert check_model_output(tmp_path / "fwd_0.5hz") == tmp_path / "fwd_0.5hz.json"
    assert not (tmp_path / "new").exists()  # checked, nothing created
