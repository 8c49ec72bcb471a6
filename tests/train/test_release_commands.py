"""benchmarks/release_weights.py: the JSON beside released weights names every training stage that made them, first
stage first, so a fine-tune in stages (one run started from another run's checkpoint) can be replayed."""
import importlib.util
import os
import shlex
import shutil
import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.conftest import REPO


def _module():
    spec = importlib.util.spec_from_file_location("release_weights", REPO / "benchmarks" / "release_weights.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _run(root, name, init):
    run = root / name
    (run / "checkpoints").mkdir(parents=True)
    cmd = ["train", "--model", "fusesr-l", "-o", str(run), "--set", f'run.init_from="{init}"', "--max-steps", "10"]
    (run / "command.txt").write_text("blendsr " + " ".join(shlex.quote(w) for w in cmd) + "\n")
    return run


def test_commands_list_the_stages_a_run_started_from(tmp_path):
    rw = _module()
    first = _run(tmp_path, "a", "pretrained:fusesr-l")
    second = _run(tmp_path, "b", str(first / "checkpoints" / "last.pt"))
    third = _run(tmp_path, "c", str(second / "checkpoints" / "last.pt"))
    args = SimpleNamespace(script="benchmarks/pretrain.sh", env="LR=1e-4", dataset="ds", runs=tmp_path)
    cmds = rw.commands(args, {"spec": {"file": "spec.toml"}}, "fusesr-l", third, 10)
    assert cmds[0].startswith("SPEC=spec.toml LR=1e-4 benchmarks/pretrain.sh")
    assert len(cmds) == 4
    assert [f"-o {r}" in c for r, c in zip((first, second, third), cmds[1:])] == [True] * 3
    assert rw.earlier_stages(first) == []  # a run from the shipped weights has no earlier stage here


def test_a_run_that_names_itself_does_not_loop(tmp_path):
    rw = _module()
    run = tmp_path / "a"
    run = _run(tmp_path, "a", str(run / "checkpoints" / "last.pt"))
    assert rw.earlier_stages(run) == []


def test_weights_fine_tuned_in_stages_name_the_shipped_weights_they_started_from(tmp_path):
    from training.pretrained import PRETRAINED
    rw = _module()
    weights = tmp_path / "weights"
    weights.mkdir()
    (weights / PRETRAINED["fusesr-l"]).with_suffix(".json").write_text(
        '{"sha256": "abc", "step": 7, "commands": ["blendsr train --model fusesr-l"]}')
    first = _run(tmp_path, "a", "pretrained:fusesr-l?residual_clamp=lr-range")
    second = _run(tmp_path, "b", str(first / "checkpoints" / "last.pt"))
    assert rw.stage_runs(second) == [first, second]
    origin = rw.shipped_origin(rw.stage_runs(second), weights)
    assert (origin["sha256"], origin["step"], origin["commands"]) == ("abc", 7, ["blendsr train --model fusesr-l"])
    assert origin["weights"].startswith("pretrained:fusesr-l?residual_clamp=lr-range as shipped before")
    other = _run(tmp_path, "c", "runs/elsewhere/checkpoints/last.pt")  # not shipped weights, no run directory
    assert rw.shipped_origin(rw.stage_runs(other), weights) is None


STUB_PY = """#!/bin/bash
# stands in for the venv's python: "dataset" holds the folder as blendsr's lock does and is refused while another
# holds it; train and the rest print what they were asked and succeed
if [ "$3" = dataset ]; then
  mkdir -- "$6.busy" 2>/dev/null || { echo "another 'blendsr dataset' is running on this folder"; exit 2; }
  sleep 2; rmdir -- "$6.busy"; echo dataset-done; exit 0
fi
echo "$3"
"""


@pytest.mark.skipif(shutil.which("flock") is None or shutil.which("bash") is None, reason="needs bash and flock")
def test_two_pretrain_runs_side_by_side_take_turns_on_the_dataset(tmp_path):
    """Two ``benchmarks/pretrain.sh`` started together on one dataset both train: the second waits for the first's
    dataset step instead of failing on the dataset folder's lock."""
    stub = tmp_path / "py"
    stub.write_text(STUB_PY)
    stub.chmod(0o755)
    env = {**os.environ, "PY": str(stub), "MODELS": "fusesr-fast", "RELEASE": "0"}
    script = str(Path(REPO) / "benchmarks" / "pretrain.sh")
    procs = []
    for name in ("a", "b"):
        procs.append(subprocess.Popen(["bash", script, str(tmp_path / "ds"), str(tmp_path / name)], env=env,
                                      cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      text=True))
        time.sleep(0.3)
    outs = [p.communicate(timeout=60)[0] for p in procs]
    for p, out in zip(procs, outs):
        assert p.returncode == 0, out
        assert "dataset-done" in out and "train" in out.split("dataset-done")[1], out


def _val_index(root: Path, groups: list[str]) -> list[str]:
    """An index of val clips of the given family groups; their folders, in order."""
    import json
    from gbuffer_export.dataset.build import INDEX, SCHEMA, SCHEMA_VERSION
    clips = [{"id": f"v{i}", "path": f"clips/v{i}", "split": "val", "state": "done", "family_group": g}
             for i, g in enumerate(groups)]
    root.mkdir()
    (root / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "clips": clips}))
    return [str(root / c["path"]) for c in clips]


def test_the_val_rule_reads_the_held_out_family_val_clips_when_there_are_any(tmp_path):
    rw = _module()
    val = _val_index(tmp_path / "ds", ["in-family", "held-out", "in-family", "held-out"])
    assert rw.rule_val_clips(tmp_path / "ds", val, "auto") == ([val[1], val[3]], "held-out")
    assert rw.rule_val_clips(tmp_path / "ds", val, "held-out") == ([val[1], val[3]], "held-out")
    assert rw.rule_val_clips(tmp_path / "ds", val, "all") == (val, "all")
    # a planned held-out clip not finished yet: refused, not read in part nor replaced by the in-family ones
    for finished in (val[:3], [val[0], val[2]]):
        with pytest.raises(ValueError, match="of its 2 held-out-family val clips are not finished"):
            rw.rule_val_clips(tmp_path / "ds", finished, "auto")
    assert rw.rule_val_clips(tmp_path / "ds", [val[0], val[2]], "all") == ([val[0], val[2]], "all")
    plain = _val_index(tmp_path / "plain", ["in-family", "in-family"])  # a dataset without held-out families
    assert rw.rule_val_clips(tmp_path / "plain", plain, "auto") == (plain, "all")
    with pytest.raises(ValueError, match="the index plans no held-out-family val clip"):
        rw.rule_val_clips(tmp_path / "plain", plain, "held-out")


def test_a_scaling_run_is_released_from_its_own_folder_with_its_own_command_and_clips(tmp_path):
    """release_weights --run MODEL=DIR --script '': a run of benchmarks/data_scaling.py (its command.txt, written
    there, is the whole command) trained on a subset: the JSON lists the subset, not the whole train split."""
    import sys
    sys.path.insert(0, str(REPO / "benchmarks"))
    import data_scaling
    rw = _module()
    run = tmp_path / "fusesr_470clips"
    data_scaling.write_command(run, ["datasets/scale", "-o", "out dir", "--model", "fusesr"])
    data_scaling.write_command(run, ["other"])  # kept when the run resumes
    text = (run / "command.txt").read_text()
    assert text == ".venv/bin/python benchmarks/data_scaling.py datasets/scale -o 'out dir' --model fusesr\n"
    args = SimpleNamespace(script="", env="", dataset="ds", runs=tmp_path)
    assert rw.commands(args, {"spec": {"file": "s.toml"}}, "fusesr", run, 10) == [text.strip()]
    with pytest.raises(ValueError, match="holds no checkpoints/last.pt"):
        rw.named_runs([f"fusesr={run}"], ["fusesr"])
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "last.pt").write_bytes(b"")
    assert rw.named_runs([f"fusesr={run}"], ["fusesr", "fusesr-l"]) == {"fusesr": run}
    with pytest.raises(ValueError, match="MODEL one of --models"):
        rw.named_runs([f"nsrd={run}"], ["fusesr"])
    with pytest.raises(ValueError, match="fusesr is given twice"):
        rw.named_runs([f"fusesr={run}", f"fusesr={run}"], ["fusesr"])
    # --script '' with no command.txt: the training command alone, not an empty script line
    bare = tmp_path / "bare"
    assert rw.commands(args, {"spec": {"file": "s.toml"}}, "fusesr", bare, 10) == [
        f"blendsr train --model fusesr --data ds -o {bare} --config benchmarks/pretrain.toml --max-steps 10 "
        "--set run.threads=1"]
    ck = {"config": {"data": {"clips": ["/d/clips/a", "/d/clips/b"]}}}
    assert rw.trained_on(ck, ["a", "b", "c"]) == ["a", "b"]
    assert rw.trained_on({"config": {"data": {}}}, ["a", "b", "c"]) == ["a", "b", "c"]


def test_the_val_rule_leaves_out_held_out_clips_whose_families_the_shipped_weights_trained_on(tmp_path, monkeypatch,
                                                                                               capsys):
    """The shipped networks trained on the wide set, which holds families the scale set holds out of train (the room
    level): such a val clip would favour the incumbent (and one the candidate's own stages saw, the candidate), so
    the rule reads only the clips neither network trained on every family of."""
    import json

    from gbuffer_export.dataset import family_gap
    from gbuffer_export.dataset.build import INDEX, SCHEMA, SCHEMA_VERSION
    rw = _module()
    ds = tmp_path / "ds"
    ds.mkdir()
    fams = {"room": ["level:room", "hdri:a"], "ship": ["asset:ship", "hdri:a"], "mixed": ["level:room", "hdri:b"]}
    (ds / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "clips": [
        {"id": n, "path": f"clips/{n}", "split": "val", "family_group": "held-out", "families": f}
        for n, f in fams.items()]}))
    val = [str(ds / "clips" / n) for n in fams]
    shipped = tmp_path / "fusesr_x4.json"
    shipped.write_text("{}")
    seen_by = {}
    monkeypatch.setattr(family_gap, "lineage_families", lambda js, repo: (seen_by[Path(js).name], ["a note"]))
    seen_by["fusesr_x4.json"] = {"level:room", "hdri:a"}
    assert rw.unseen_val_clips(ds, val, "held-out", shipped) == ([val[1], val[2]], [val[0]])
    assert "note: a note" in capsys.readouterr().err
    assert rw.unseen_val_clips(ds, val, "all", shipped) == (val, [])  # only the held-out group is filtered
    assert rw.unseen_val_clips(ds, val, "held-out", tmp_path / "none.json") == (val, [])  # nothing shipped yet
    seen_by["fusesr_x4.json"] = {"level:room", "hdri:a", "hdri:b", "asset:ship"}
    with pytest.raises(ValueError, match="trained on every family of all 3 held-out-family val clips"):
        rw.unseen_val_clips(ds, val, "held-out", shipped)

    def no_lineage(js, repo):
        raise ValueError(f"{js}: no training lineage")
    monkeypatch.setattr(family_gap, "lineage_families", no_lineage)
    assert rw.unseen_val_clips(ds, val, "held-out", shipped) == (val, [])
    assert "no training lineage; only the candidate's own lineage counts" in capsys.readouterr().err
    # the candidate's lineage counts too: a run that trained on the ship and HDRI a leaves that clip out
    seen_by["fusesr_x4.json"] = {"level:room", "hdri:a"}
    monkeypatch.setattr(family_gap, "lineage_families", lambda js, repo: (seen_by[Path(js).name], []))
    assert rw.unseen_val_clips(ds, val, "held-out", shipped, {"asset:ship", "hdri:a"}) == ([val[2]], [val[0], val[1]])
    # either network alone, not the two together: "mixed" (the room seen by one, HDRI b by the other) stays
    assert rw.unseen_val_clips(ds, val, "held-out", shipped, {"hdri:b"}) == ([val[1], val[2]], [val[0]])


def test_a_fine_tune_names_what_it_started_from_and_is_refused_once_those_weights_are_no_longer_shipped(tmp_path,
                                                                                                      monkeypatch,
                                                                                                      capsys):
    """A run started from ``pretrained:NAME`` records the sha256 of the file it read (``training.train.init_record``,
    in every checkpoint); released after another release replaced those weights, its JSON would name the wrong origin
    and lineage, so release_weights refuses it. Its init is read from config.toml when there is no command.txt; its
    own clips' families (every stage) come from the dataset's index."""
    import json

    from gbuffer_export.dataset.build import INDEX, SCHEMA, SCHEMA_VERSION
    rw = _module()
    weights = tmp_path / "weights"
    weights.mkdir()
    (weights / "fusesr_l_x4.json").write_text(json.dumps({"sha256": "b" * 64, "dataset": {"spec_file": "w.toml",
                                                          "train_clips": ["x"]}, "commands": ["SPEC=w.toml run"]}))
    run = tmp_path / "ft"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.toml").write_text('[data]\nclips = ["/d/clips/a"]\n[run]\ninit_from = "pretrained:fusesr-l"\n')
    assert rw.init_of(run) == "pretrained:fusesr-l"
    rw.check_origin(run, {"init": {"from": "pretrained:fusesr-l", "sha256": "b" * 64}}, weights)  # still shipped
    rw.check_origin(run, {}, weights)  # a run from before the record: a note, the weights shipped now assumed
    assert "is not recorded (no init in its checkpoint, no init.json)" in capsys.readouterr().err
    with pytest.raises(ValueError, match="started from pretrained:fusesr-l with sha256 aaaa.*a release after it"):
        rw.check_origin(run, {"init": {"from": "pretrained:fusesr-l", "sha256": "a" * 64}}, weights)
    (run / "init.json").write_text(json.dumps({"from": "pretrained:fusesr-l", "sha256": "a" * 64}))  # by hand
    with pytest.raises(ValueError, match="a release after it started"):
        rw.check_origin(run, {}, weights)
    # the same tensors under a new header (benchmarks/ship_option.py): the parameter digest agrees
    (weights / "fusesr_l_x4.json").write_text(json.dumps({"sha256": "b" * 64, "param_digest": "p1", "dataset": {
        "spec_file": "w.toml", "train_clips": ["x"]}, "commands": ["SPEC=w.toml run"]}))
    rw.check_origin(run, {"init": {"sha256": "a" * 64, "param_digest": "p1"}}, weights)
    with pytest.raises(ValueError, match="a release after it started"):
        rw.check_origin(run, {"init": {"sha256": "a" * 64, "param_digest": "p0"}}, weights)
    (run / "init.json").unlink()
    origin = rw.shipped_origin([run], weights)
    assert origin["dataset"] == {"spec_file": "w.toml", "train_clips": ["x"]} and origin["sha256"] == "b" * 64
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / INDEX).write_text(json.dumps({"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "clips": [
        {"id": n, "path": f"clips/{n}", "split": "train", "families": [f"asset:{n}"]} for n in ("a", "b", "c")]}))
    second = tmp_path / "ft2"
    (second / "checkpoints").mkdir(parents=True)
    (second / "command.txt").write_text(f"blendsr train --set run.init_from={run}/checkpoints/last.pt\n")
    (run / "command.txt").write_text("blendsr train --set run.init_from=pretrained:fusesr-l\n")
    loaded = {"config": {"data": {"clips": ["/d/clips/b"]}}}
    from gbuffer_export.dataset import family_gap  # the first stage started from the shipped weights: their lineage
    monkeypatch.setattr(family_gap, "lineage_families", lambda js, repo: ({"level:room"}, []))
    assert rw.candidate_families(ds, rw.stage_runs(second), loaded, weights) == {"asset:a", "asset:b", "level:room"}
    scratch = tmp_path / "scratch"
    (scratch / "checkpoints").mkdir(parents=True)
    assert rw.candidate_families(ds, [scratch], {"config": {"data": {"clips": ["/d/clips/c"]}}}, weights) == {"asset:c"}
    # a stage with no command.txt is still a stage (its config.toml), named by its configuration
    (run / "command.txt").unlink()
    assert rw.stage_runs(second) == [run, second]
    assert "(no command.txt: the stage's configuration)" in rw.earlier_stages(second)[0]


def test_a_run_that_has_not_finished_is_not_released(tmp_path):
    """The weights scored must be those shipped: a run still training (or interrupted) is refused unless --force."""
    import json
    rw = _module()
    run = tmp_path / "r"
    run.mkdir()
    with pytest.raises(ValueError, match="step 1200, and the run has not finished there .summary.json: none"):
        rw.check_finished(run, {"step": 1200}, False)
    rw.check_finished(run, {"step": 1200}, True)
    (run / "summary.json").write_text(json.dumps({"step": 1000, "stopped_by": "interrupted"}))
    with pytest.raises(ValueError, match="interrupted at step 1000"):
        rw.check_finished(run, {"step": 1200}, False)
    (run / "summary.json").write_text(json.dumps({"step": 1200, "stopped_by": "max_steps"}))
    rw.check_finished(run, {"step": 1200}, False)


def test_an_inference_option_left_out_of_a_configuration_counts_as_its_default():
    """An older shipped configuration without ``transmission_fallback`` runs it at its default (False): no note;
    a bound that differs is named."""
    rw = _module()
    old = {"model": {"fusesr-l": {"residual_clamp": "lr-range"}}}
    new = {"model": {"fusesr-l": {"residual_clamp": "lr-guided", "transmission_fallback": False}}}
    assert rw.option_note(new, old, "fusesr-l") == ("note: fusesr-l: the candidate runs with residual_clamp "
                                                    "'lr-guided' (shipped: 'lr-range'); --options sets them")
    assert rw.option_note({"model": {"fusesr-l": {"transmission_fallback": False}}}, {"model": {}}, "fusesr-l") is None
    assert "transmission_fallback True (shipped: False)" in rw.option_note(
        {"model": {"fusesr-l": {"transmission_fallback": True}}}, {}, "fusesr-l")
