"""What the CLI prints (issue 36): help that documents every option, tables that are not
squeezed, messages that show what differs, one definition of the task counts, one log
format on the console, and refusals before a cluster starts."""

from __future__ import annotations

import io
import json
import logging
import re
import shutil
import subprocess
import sys

import pytest


def _cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "schlieren.workers.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env={**__import__("os").environ,
                                                                                "COLUMNS": "80"})


def _help(*command) -> str:
    from schlieren.workers.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    p = sub.choices[command[0]]
    return p.format_help()


def _options(help_text: str) -> dict[str, str]:
    """Option -> its help text, from an argparse help page."""
    out, current = {}, None
    for line in help_text.split("options:", 1)[1].splitlines():
        m = re.match(r"  (-{1,2}[\w-]+)", line)
        if m:
            current = m.group(1)
            out[current] = line[len(m.group(0)):].strip()
        elif current and line.strip():
            out[current] += " " + line.strip()
    return out


def test_every_synth_option_has_help_and_its_default():
    opts = _options(_help("synth"))
    assert len(opts) > 15
    flags = {"--video", "--no-strobe", "--distortion", "--background-only", "-h"}
    for name, text in opts.items():
        words = re.sub(r"^[A-Z_{},\d.\[\] -]+\s", "", text)  # the metavar
        assert len(words.split()) >= 3, (name, text)
        if name not in flags:
            assert "default" in text, (name, text)


def test_export_help_lists_every_format():
    from schlieren.storage.export import FORMATS
    from schlieren.workers.cli import build_parser

    text = _help("export")
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    one_line = next(c.help for c in sub._choices_actions if c.dest == "export")
    for fmt in FORMATS:
        assert fmt in one_line, one_line
        assert fmt in text.split("positional arguments:")[0].split("usage:", 1)[1].split("\n\n", 1)[1], text


def test_init_help_shows_images_as_well_as_videos():
    text = _help("init")
    usage = text.split("\n\n")[0]
    assert "--images" in usage and "--videos" in usage, usage
    opts = _options(text)
    assert "image sequence" in opts["--images"] and "video" in opts["--videos"]


def test_evaluate_keeps_its_table_whole_when_not_on_a_terminal(tiny_session, serial_store):
    p = _cli("evaluate", serial_store, "--truth", tiny_session.truth)
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    header = next(ln for ln in lines if "frame" in ln and "PSNR" in ln)
    for col in ("time (s)", "RMS (%)", "PSNR (dB)", "in-plume RMS (%)", "in-plume PSNR (dB)", "peak ratio"):
        assert col in header, header
    rows = [ln for ln in lines if re.match(r"^\W*\s*\d+\s", ln)]
    assert len(rows) == 3 and all(len(re.findall(r"-?\d+\.\d+", r)) >= 6 for r in rows), p.stdout


def test_a_fingerprint_mismatch_shows_where_the_two_sides_differ():
    from schlieren.storage.store.attrs import differences

    cams = [{"name": f"cam{i:02d}", "frames": f"cam{i:02d}/frames/%05d.png",
             "K": [[1091.63389616684, 0.0, 95.5], [0.0, 1091.63389616684, 71.5], [0.0, 0.0, 1.0]]}
            for i in range(4)]
    other = json.loads(json.dumps(cams))
    other[2]["K"][0][0] = 1100.0
    name = "synthetic-blob-4half-" + "x" * 60
    diff = differences({"session": {"cameras": cams, "name": name}},
                       {"session": {"cameras": other, "name": name + "y"}})
    assert len(diff) == 2, diff
    for d in diff:
        where, change = d.split(": ", 1)
        old, new = change.split(" -> ")
        assert old != new, d
    assert diff[0].startswith("session.cameras[2].K[0][0]: 1091.63389616684 -> 1100.0"), diff
    assert diff[1].startswith("session.name: ...") and diff[1].endswith('xx" -> ...' + "x" * 38 + 'y"'), diff


def test_task_counts_mean_the_same_on_a_first_and_a_resumed_run(tiny_session, serial_store, tmp_path):
    from schlieren.storage.store import ResultStore

    store = tmp_path / "s.zarr"
    shutil.copytree(serial_store, store)
    st = ResultStore.open(store)
    total = sum(int(st.array(f"status/{s}").size) for s in st.stages())
    for j in range(st.array("status/deflection").shape[1]):
        st.unmark("deflection", (0, j))  # batched: several frames a task
    n = st.array("status/deflection").shape[1]

    def counts(p):
        m = re.search(r"\((\d+) steps computed in (\d+) tasks?, (\d+) already complete", p.stderr)
        assert m, p.stderr
        return tuple(int(v) for v in m.groups())

    p = _cli("run", tiny_session.session, "--out", store, "--serial", "--no-progress")
    assert p.returncode == 0, p.stderr
    computed, tasks, complete = counts(p)
    assert computed == n and tasks < n and complete == total - n
    p = _cli("run", tiny_session.session, "--out", store, "--serial", "--no-progress")
    assert counts(p) == (0, 0, total)


def test_worker_log_lines_are_plain_on_the_console():
    from schlieren.workers.monitoring import configure_worker_logging

    stream = io.StringIO()
    configure_worker_logging("schlieren.test_console", level="WARNING", stream=stream)
    logging.getLogger("schlieren.test_console.tasks").warning("camera %s, frame %d: dropped by the camera", "cam01", 41)
    line = stream.getvalue().strip()
    assert line == "WARNING schlieren.test_console.tasks: camera cam01, frame 41: dropped by the camera", line


def test_the_worker_plugin_logs_plain_lines_to_stderr_and_json_to_files(tmp_path, capsys):
    from schlieren.workers.cluster.worker_setup import SchlierenWorkerSetup

    class Worker:
        name = "w0"
        address = "tcp://127.0.0.1:1"

    lg = logging.getLogger("schlieren")
    saved = (list(lg.handlers), lg.level, lg.propagate)
    try:
        SchlierenWorkerSetup(log_level="WARNING").setup(Worker())
        logging.getLogger("schlieren.workers.tasks.deflection").warning("camera cam01, frame 41: dropped")
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert not err.startswith("{") and err.endswith("camera cam01, frame 41: dropped"), err
        SchlierenWorkerSetup(log_level="WARNING", log_dir=str(tmp_path)).setup(Worker())
        logging.getLogger("schlieren.workers.tasks.deflection").warning("camera cam02: x")
        for h in lg.handlers:
            h.flush()
        assert json.loads((tmp_path / "w0.jsonl").read_text().splitlines()[-1])["message"] == "camera cam02: x"
    finally:
        for h in list(lg.handlers):
            if h not in saved[0]:
                lg.removeHandler(h)
                h.close()
        lg.handlers[:] = saved[0]
        lg.setLevel(saved[1])
        lg.propagate = saved[2]


@pytest.mark.system
def test_run_out_on_a_folder_that_is_not_a_store_is_refused_before_a_cluster_starts(tiny_session, tmp_path):
    out = tmp_path / "results"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    p = _cli("run", tiny_session.session, "--out", out, "--workers", "2", timeout=120)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(out) in lines[0] and "not a result store" in lines[0], p.stderr
    assert (out / "notes.txt").read_text() == "mine" and sorted(p.name for p in out.iterdir()) == ["notes.txt"]
