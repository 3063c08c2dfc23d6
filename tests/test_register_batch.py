"""vrnet register-batch: one record per pair in manifest order, the same transforms as register(),
failures recorded, a killed run resumed to every pair once, torchrun shards merged."""
import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from synthetic import motion
from vrnet_ext.data.procedural import room_scan
from vrnet_ext.cli import main
from vrnet_ext.geometry.transforms import apply
from vrnet_ext.registration import IcpSettings, register
from vrnet_ext.registration import batch as batch_module
from vrnet_ext.registration.batch import BatchOptions, merge, read_manifest, register_batch

FAST = ["--icp-points", "3000", "--global-points", "1500"]


@pytest.fixture()
def manifest(tmp_path):
    """Three pairs of room scans with ground truth (one scan in two pairs) and one missing file."""
    rows = ["id,source,target,gt"]
    scans = {name: room_scan(8000, seed) for seed, name in enumerate(("a", "b", "c"))}
    for name, points in scans.items():
        np.save(tmp_path / f"{name}.npy", points)
    for number, (src, tgt, degrees) in enumerate((("a", "b", 20.0), ("a", "c", 35.0), ("b", "c", 10.0))):
        truth = motion(degrees, [0.2, -0.1, 0.05], seed=number)
        np.save(tmp_path / f"{tgt}_{number}.npy", apply(truth, scans[tgt]))
        np.savetxt(tmp_path / f"gt_{number}.txt", truth)
        rows.append(f"pair{number},{src}.npy,{tgt}_{number}.npy,gt_{number}.txt")
    rows.append("broken,a.npy,missing.npy,")
    (tmp_path / "pairs.csv").write_text("\n".join(rows) + "\n")
    return tmp_path / "pairs.csv"


def records(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_one_record_per_pair_with_the_transform_of_register(manifest, tmp_path, capsys):
    out = tmp_path / "results.jsonl"
    assert main(["register-batch", str(manifest), "--out", str(out), "--no-progress", *FAST]) == 0
    assert "pairs 4, failed 1, with_ground_truth 3, recall 1" in capsys.readouterr().out
    got = records(out)
    assert [r["id"] for r in got] == ["pair0", "pair1", "pair2", "broken"]
    assert "missing.npy: no such file" in got[3]["error"]
    assert all(r["registered"] and r["errors"]["rotation_error_deg"] < 1.0 for r in got[:3])
    task = read_manifest(manifest)[1]
    single = register(np.load(task.source), np.load(task.target), global_points=1500,
                      icp_settings=IcpSettings(points=3000))
    assert got[1]["T_target_source"] == single.T_target_source.tolist()  # bit for bit, as a single pair
    assert not list(tmp_path.glob("results.jsonl.part*"))


def test_a_killed_run_resumes_to_every_pair_once(manifest, tmp_path, monkeypatch):
    class Killed(BaseException):
        pass

    real, calls = batch_module.register_pair, []

    def dies_on_the_second(task, read, options):
        calls.append(task.index)
        if len(calls) == 2:
            raise Killed
        return real(task, read, options)

    monkeypatch.setattr(batch_module, "register_pair", dies_on_the_second)
    options = BatchOptions(register=dict(global_points=1500, icp_settings=IcpSettings(points=3000)))
    out = tmp_path / "results.jsonl"
    with pytest.raises(Killed):
        register_batch(manifest, out, options, progress=False)
    part = next(tmp_path.glob("results.jsonl.part*"))
    part.write_text(part.read_text() + '{"index": 1, "id": "pair1", "T_tar')  # a record torn by the kill
    monkeypatch.setattr(batch_module, "register_pair", real)
    register_batch(manifest, out, options, progress=False)
    merged = merge(manifest, out)
    assert [r["index"] for r in merged] == [0, 1, 2, 3] and calls == [0, 1]


def test_manifests_are_checked_naming_the_file_and_the_pair(tmp_path):
    (tmp_path / "m.csv").write_text("source,target\na.npy,\n")
    with pytest.raises(ValueError, match="m.csv: pair 1 needs a source and a target"):
        read_manifest(tmp_path / "m.csv")
    (tmp_path / "m.jsonl").write_text('{"source": "a.npy", "target": "b.npy"}\nnot json\n')
    with pytest.raises(ValueError, match="m.jsonl: line 2 is not JSON"):
        read_manifest(tmp_path / "m.jsonl")
    tasks = read_manifest(_tsv(tmp_path))
    assert tasks[0].id == "p" and tasks[0].gt == (tmp_path / "gt" / "p.txt").resolve()


def _tsv(folder):
    """The real-pairs manifest layout (pair_id, source_file, target_file, gt_file)."""
    (folder / "MANIFEST.tsv").write_text("pair_id\tsource_file\ttarget_file\tgt_file\np\tclouds/a.npy\tclouds/b.npy\t"
                                         "gt/p.txt\n")
    return folder / "MANIFEST.tsv"


@pytest.mark.skipif(shutil.which("torchrun") is None, reason="torchrun not found")
def test_two_torchrun_processes_merge_to_the_single_process_file(manifest, tmp_path):
    """2 processes of 1 thread each give the records of one process of all threads, bit for bit."""
    single, sharded = tmp_path / "single.jsonl", tmp_path / "sharded.jsonl"
    assert main(["register-batch", str(manifest), "--out", str(single), "--no-progress", *FAST]) == 0
    env = dict(os.environ, OMP_NUM_THREADS="1")
    done = subprocess.run(["torchrun", "--nproc-per-node", "2", "-m", "vrnet_ext.cli", "register-batch", str(manifest),
                           "--out", str(sharded), "--no-progress", *FAST], capture_output=True, text=True, env=env,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    drop = ("seconds",)
    assert [{k: v for k, v in r.items() if k not in drop} for r in records(sharded)] == \
        [{k: v for k, v in r.items() if k not in drop} for r in records(single)]


def test_torchrun_ranks_take_their_own_gpu_or_share_them_in_turn():
    from vrnet_ext.cli.batch import rank_device

    assert [rank_device("cuda", rank, 2) for rank in range(4)] == ["cuda:0", "cuda:1", "cuda:0", "cuda:1"]
    assert rank_device("cuda", 3, 8) == "cuda:3" and rank_device("cuda:1", 3, 8) == "cuda:1"
    assert rank_device("cpu", 3, 8) == "cpu" and rank_device("cuda", 0, 0) == "cuda"
