"""`cubecloud cohort` on Snakemake: tiny scans locally, then on a real one-node SLURM cluster
(tests/slurm_cluster.py) or, where SLURM cannot be installed, through the generic cluster
executor; a corrupt scan among them, and a job stopped mid-way resumed by the next run."""

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from cli_helpers import assert_one_line_error, invoke
from slurm_cluster import INIT_SECONDS_BEFORE_STATUS_CHECKS, local_cluster, unavailable_because

from cubecloud_cli.cohort.engine import wait_passing_on_interrupts
from cubecloud_cli.cohort.scans import CohortScan, scans_from_csv
from cubecloud_cli.cohort.workflow import interrupted_message
from cubecloud_cli.sample_data import sample_ct_path

pytestmark = pytest.mark.slow  # runs first: pytest-xdist's workers then end together

pytest.importorskip("snakemake", reason="needs the cohort extra: pip install 'cubecloud[cohort]'")

TINY = ["--size", "32", "--cunerf-iterations", "60", "--splat-iterations", "60", "--views", "8", "--resolution", "32"]


def scans_folder(folder, good: int = 3, corrupt: bool = False):
    folder.mkdir(parents=True)
    for number in range(good):
        shutil.copy(sample_ct_path(), folder / f"case{number}.nii.gz")
    if corrupt:
        (folder / "broken.nii.gz").write_bytes(b"not a scan")
    return folder


def rows(out):
    return {row["id"]: row for row in csv.DictReader(open(out / "cohort" / "per_scan.csv"))}


@pytest.fixture(scope="module")
def local_cohort(tmp_path_factory):
    """Two scans and a corrupt one through a local cohort: the outcome, and the folders."""
    root = tmp_path_factory.mktemp("cohort")
    scans, out = scans_folder(root / "scans", good=2, corrupt=True), root / "out"
    return invoke("cohort", scans, "-o", out, "--cores", "2", *TINY, "-q"), scans, out


def test_two_scans_and_a_corrupt_one_run_locally_and_the_report_lists_the_failure(local_cohort):
    result, _, out = local_cohort
    error = assert_one_line_error(result, r"1 of 3 scans failed \(broken: preprocess: cannot read .*broken\.nii\.gz")
    assert "report.md" in error
    table = rows(out)
    assert [table[f"case{n}"]["status"] for n in range(2)] == ["done"] * 2 and table["broken"]["status"] == "failed"
    for number in range(2):  # each scan is a normal work directory
        assert (out / f"case{number}" / "eval" / "metrics.json").is_file()
        assert float(table[f"case{number}"]["splat_novel_psnr"]) > 10.0
    report = (out / "cohort" / "report.md").read_text()
    assert "3 scans, 2 finished." in report and "| Cube-Cloud 3DGS |" in report and "| broken |" in report
    assert not (out / "broken" / "eval").exists()
    assert not (out / "cohort" / "lock").exists()
    launcher = json.loads((out / "cohort" / "config.json").read_text())["cubecloud"]
    assert launcher[1:3] == ["-m", "cubecloud_cli.cohort.job_client"]  # jobs here start through the job server
    assert not Path(launcher[3]).exists()  # which stopped with the cohort


def exported_scan(local_cohort, tmp_path):
    """The local cohort's first scan with its stages up to export (a scans folder and an output
    folder of its own): the splat runs and eval are left to run."""
    _, local_scans, local_out = local_cohort
    scans = tmp_path / "scans"
    scans.mkdir()
    shutil.copy2(local_scans / "case0.nii.gz", scans)  # older than the stages made from it
    out = tmp_path / "out"
    shutil.copytree(local_out / "case0", out / "case0")
    for stage in ("splat", "splat-random", "eval"):
        shutil.rmtree(out / "case0" / stage)
    return scans, out


def cluster_profile(folder: Path) -> Path:
    """A Snakemake profile for the generic cluster executor whose "cluster" is this machine: the
    submit command gets the job script last, starts it in the background and prints an id."""
    folder.mkdir()
    (folder / "config.yaml").write_text(
        "executor: cluster-generic\n"
        'cluster-generic-submit-cmd: "sh -c \'nohup bash \\"$0\\" >/dev/null 2>&1 & echo $!\'"\n'
        "jobs: 2\n"
        "latency-wait: 5\n"
        "seconds-between-status-checks: 1\n"
    )
    return folder


@pytest.mark.skipif(
    not unavailable_because(),
    reason="SLURM can run here: `pytest -m cluster` stops a cohort's job on it and resumes it",
)
def test_a_cohort_on_the_cluster_executor_killed_mid_way_resumes_where_it_stopped(local_cohort, tmp_path):
    """The local cohort's first scan, its stages up to export kept: the generic cluster executor
    submits the two splat runs and eval, each job a process of its own. The cohort is killed while
    a splat stage trains (as a cluster would kill it, jobs and all), and the same command finishes
    it without redoing the stages before. (One scan's whole pipeline, each stage paying Python's
    and torch's start, would take a minute here.)"""
    scans, out = exported_scan(local_cohort, tmp_path)
    kept = {
        stage: (out / "case0" / stage / "manifest.json").stat().st_mtime_ns
        for stage in ("preprocess", "cunerf", "export")
    }
    options = [str(scans), "-o", str(out), "--profile", str(cluster_profile(tmp_path / "profile")), *TINY, "-q"]
    command = [sys.executable, "-m", "cubecloud_cli", "cohort", *options]
    process = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    training = [out / "case0" / ".splat.partial", out / "case0" / ".splat-random.partial"]
    deadline = time.monotonic() + 300
    while not any(p.exists() for p in training) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert any(p.exists() for p in training), "the cohort never started a splat stage"
    os.killpg(process.pid, signal.SIGKILL)  # the cohort, Snakemake and the submitted jobs
    process.wait()
    assert not (out / "case0" / "eval" / "manifest.json").exists()

    result = invoke("cohort", *options)
    assert result.exit_code == 0, result.output
    assert rows(out)["case0"]["status"] == "done"
    assert (out / "case0" / "eval" / "metrics.json").is_file()
    assert sorted(p.name for p in (out / "cohort" / "logs" / "case0").iterdir()) == [
        "eval.log",
        "splat-random.log",
        "splat.log",
    ]
    assert {stage: (out / "case0" / stage / "manifest.json").stat().st_mtime_ns for stage in kept} == kept
    assert "--profile" in (out / "cohort" / "snakemake_command.txt").read_text()
    launcher = json.loads((out / "cohort" / "config.json").read_text())["cubecloud"]
    assert launcher[1:] == ["-m", "cubecloud_cli"]  # an executor may send jobs elsewhere: no job server


# A stage's results: the same bits on the cluster as from the local cohort.
RESULT_FILES = {
    "preprocess": ["volume.npy"],
    "cunerf": ["model.pt"],
    "export": ["images.npy", "reference.npy", "points3D.ply", "novel/reference.npy"],
    "splat": ["point_cloud.ply"],
    "splat-random": ["point_cloud.ply"],
}
SUBMITTED = re.compile(r"submitted with SLURM jobid (\d+) \(log: .*/rule_(\w+)/(\w+)/\d+\.log\)")


def results(work: Path) -> dict:
    """The sha256 of each result file, as the stages' manifests record them, and eval's scores."""
    digests = {}
    for stage, names in RESULT_FILES.items():
        files = json.loads((work / stage / "manifest.json").read_text())["files"]
        digests.update({f"{stage}/{name}": files[name]["sha256"] for name in names})
    metrics = json.loads((work / "eval" / "manifest.json").read_text())["metrics"]
    digests["eval"] = {run: scores for run, scores in metrics.items() if isinstance(scores, dict)}
    return digests


def slurm_profile(folder: Path) -> Path:
    """examples/slurm with the test cluster's partition and the README's settings for a cluster
    without accounting (polling with squeue; the first status check soon, for a test)."""
    folder.mkdir()
    text = (Path(__file__).resolve().parents[1] / "examples" / "slurm" / "config.yaml").read_text()
    text = text.replace('slurm_partition: "cpu"', 'slurm_partition: "debug"')
    text += (
        "slurm-status-command: squeue\n"
        f"slurm-init-seconds-before-status-checks: {INIT_SECONDS_BEFORE_STATUS_CHECKS}\n"
        "latency-wait: 5\n"
    )
    (folder / "config.yaml").write_text(text)
    return folder


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    """A one-node SLURM cluster on localhost, or a skip where SLURM cannot be installed."""
    if unavailable_because():
        pytest.skip(unavailable_because())
    pytest.importorskip("snakemake_executor_plugin_slurm", reason="needs snakemake-executor-plugin-slurm")
    with local_cluster(tmp_path_factory.mktemp("slurm")) as cluster:
        yield cluster


@pytest.mark.cluster  # some 4 minutes of jobs that mostly wait on the scheduler: apart from the suite
def test_a_cohort_on_slurm_gives_the_local_bits_and_resumes_a_job_stopped_by_sigterm(slurm, local_cohort, tmp_path):
    """The local cohort's first scan and its corrupt one, every stage an sbatch job. The export job
    gets SIGTERM once its bake is saved, as SLURM stops a job at its time limit or on pre-emption;
    the same command then resumes it, and finishes the scan with the local cohort's bits."""
    _, local_scans, local_out = local_cohort
    scans = tmp_path / "scans"
    scans.mkdir()
    for name in ("case0.nii.gz", "broken.nii.gz"):
        shutil.copy2(local_scans / name, scans)
    out = tmp_path / "out"
    command = [sys.executable, "-m", "cubecloud_cli", "cohort", str(scans), "-o", str(out),
               "--profile", str(slurm_profile(tmp_path / "profile")), *TINY]  # fmt: skip
    first = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    output: list[str] = []
    reader = threading.Thread(target=lambda: output.extend(first.stdout), daemon=True)
    reader.start()
    bake = out / "case0" / ".export.partial" / "progress" / "bake.npy"
    deadline = time.monotonic() + 300
    while not bake.is_file() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    assert bake.is_file(), "the export job saved no bake"
    job = next((out / ".snakemake" / "slurm_logs" / "rule_export" / "case0").glob("*.log")).stem  # its SLURM job id
    subprocess.run(["scancel", "--signal=TERM", job], check=True)
    first.wait(timeout=300)
    reader.join(timeout=10)
    assert first.returncode == 2, "".join(output)
    log = (out / "cohort" / "logs" / "case0" / "export.log").read_text()
    assert re.search(r"interrupted: \d+ of \d+ views are saved", log), log
    assert not (out / "case0" / "export" / "manifest.json").exists() and bake.is_file()

    second = subprocess.run(command, capture_output=True, text=True, timeout=300)
    errors = [line for line in second.stderr.splitlines() if line.startswith("error: ")]
    assert second.returncode == 2 and len(errors) == 1, second.stdout + second.stderr
    assert errors[0].startswith("error: 1 of 2 scans failed (broken: preprocess: cannot read"), errors[0]
    log = (out / "cohort" / "logs" / "case0" / "export.log").read_text()
    assert "continuing the interrupted export" in log and "(resumed from its saved work)" in log, log
    assert json.loads((out / "case0" / "export" / "manifest.json").read_text())["resumed"]["bake"] is True

    # Every job went through SLURM: each one the plugin submitted ended there, in this state.
    submitted = [match.groups() for match in SUBMITTED.finditer("".join(output) + second.stdout + second.stderr)]
    states = {record["JobId"]: record["JobState"] for record in slurm.completed_jobs()}
    assert sorted((rule, scan, states.get(job)) for job, rule, scan in submitted) == sorted(
        [(rule, "case0", "COMPLETED") for rule in ("preprocess", "cunerf", "export", "splat", "splat_random", "eval")]
        + [("export", "case0", "FAILED")]
        + [("preprocess", "broken", "FAILED")] * 2
    )
    launcher = json.loads((out / "cohort" / "config.json").read_text())["cubecloud"]
    assert launcher[1:] == ["-m", "cubecloud_cli"]  # no job server: each job started cubecloud on the node
    assert results(out / "case0") == results(local_out / "case0")
    assert not list((out / "broken").glob("*/manifest.json")) and rows(out)["case0"]["status"] == "done"


def test_bad_cohort_input_is_one_line(tmp_path):
    assert_one_line_error(invoke("cohort", tmp_path / "nowhere", "-o", tmp_path / "out"), r"nowhere does not exist")
    (tmp_path / "empty").mkdir()
    assert_one_line_error(invoke("cohort", tmp_path / "empty", "-o", tmp_path / "out"), r"holds no NIfTI file")
    (tmp_path / "cohort.csv").write_text("id,scan\na,missing.nii.gz\n")
    assert_one_line_error(invoke("cohort", "--scans", tmp_path / "cohort.csv", "-o", tmp_path / "out"),
                          r"cohort.csv line 2: scan 'missing.nii.gz' does not exist")  # fmt: skip
    shutil.copy(sample_ct_path(), tmp_path / "x.nii.gz")
    (tmp_path / "dup.csv").write_text("id,scan\na,x.nii.gz\na,x.nii.gz\n")
    assert_one_line_error(invoke("cohort", "--scans", tmp_path / "dup.csv", "-o", tmp_path / "out"),
                          r"two scans have the id 'a'")  # fmt: skip
    assert_one_line_error(invoke("cohort", tmp_path / "x.nii.gz", "-o", tmp_path / "out", "--profile", tmp_path / "no"),
                          r"--profile .* is not a folder")  # fmt: skip


def test_a_csv_from_a_spreadsheet_reads_and_a_bad_value_names_its_line_and_column(tmp_path):
    shutil.copy(sample_ct_path(), tmp_path / "x.nii.gz")
    (tmp_path / "bom.csv").write_text("id,scan,window\na,x.nii.gz,lung\nb,x.nii.gz,\n", encoding="utf-8-sig")
    scans = scans_from_csv(tmp_path / "bom.csv")
    assert [(s.id, s.window) for s in scans] == [("a", "lung"), ("b", None)]
    (tmp_path / "bad.csv").write_text("id,scan,window,modality\na,x.nii.gz,lung,ct\nb,x.nii.gz,lungs,ct\n")
    assert_one_line_error(invoke("cohort", "--scans", tmp_path / "bad.csv", "-o", tmp_path / "out"),
                          r"bad.csv line 3, column window: 'lungs' must be one of abdomen, .*full")  # fmt: skip
    (tmp_path / "bad.csv").write_text("id,scan,modality\na,x.nii.gz,pet\n")
    assert_one_line_error(invoke("cohort", "--scans", tmp_path / "bad.csv", "-o", tmp_path / "out"),
                          r"line 2, column modality: 'pet' must be one of auto, ct, mr")  # fmt: skip
    assert not (tmp_path / "out").exists()


def test_run_stage_runs_one_stage_only_once_the_stages_it_reads_are_current(tmp_path):
    work = tmp_path / "work"
    assert_one_line_error(invoke("run", "-o", work, "--stage", "cunerf"),
                          r"stage cunerf reads preprocess, which is missing.*run `--stage preprocess` first")  # fmt: skip
    assert_one_line_error(invoke("run", "-o", work, "--stage", "everything"), r"--stage 'everything' must be one of")
    result = invoke("run", "-o", work, "--size", "32", "--stage", "preprocess", "-q")
    assert result.exit_code == 0, result.output
    assert (work / "preprocess" / "manifest.json").is_file() and not (work / "cunerf").exists()


def test_without_snakemake_the_error_names_the_extra(tmp_path, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_snakemake(name, *args, **kwargs):
        if name == "snakemake" or name.startswith("snakemake."):
            raise ImportError("No module named 'snakemake'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_snakemake)
    shutil.copy(sample_ct_path(), tmp_path / "x.nii.gz")
    assert_one_line_error(invoke("cohort", tmp_path / "x.nii.gz", "-o", tmp_path / "out"),
                          r"runs on Snakemake, which is not installed: pip install 'cubecloud\[cohort\]'")  # fmt: skip
    assert not (tmp_path / "out").exists()


def test_ctrl_c_or_sigterm_is_passed_on_to_snakemake_and_waited_for(tmp_path):
    marker = tmp_path / "stopped"
    child = subprocess.Popen(
        [sys.executable, "-c", "import signal, sys, time\n"
         f"signal.signal(signal.SIGINT, lambda *_: (open({str(marker)!r}, 'w').write('jobs stopped'), sys.exit(3)))\n"
         "print('ready', flush=True)\ntime.sleep(120)"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert child.stdout.readline().strip() == "ready"
    timer = threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT))  # the interrupt reaches this process only
    timer.start()
    with pytest.raises(KeyboardInterrupt):
        wait_passing_on_interrupts(child)
    timer.join()
    assert child.returncode == 3 and marker.read_text() == "jobs stopped"


def test_an_interrupted_cohort_says_which_stages_it_keeps(tmp_path):
    for scan_id, stages in (("a", ["preprocess", "cunerf", "export"]), ("b", ["preprocess"]), ("c", [])):
        for stage in stages:
            (tmp_path / scan_id / stage).mkdir(parents=True)
            (tmp_path / scan_id / stage / "manifest.json").write_text("{}")
    (tmp_path / "b" / ".cunerf.partial").mkdir()  # interrupted: not complete
    scans = [CohortScan(scan_id, tmp_path / "x.nii.gz") for scan_id in "abc"]
    message = interrupted_message(tmp_path, scans)
    assert message.startswith("interrupted: 4 stages are complete and kept (0 of 3 scans finished)")
    assert "run the same cohort command again" in message
