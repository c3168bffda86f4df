"""dmcr_jax.benchmarks.profile: device events picked and grouped per op from a profiler trace
(a synthetic GPU-shaped trace, then a real CPU one), and the command end to end."""

import gzip
import json
import os

import jax
import jax.numpy as jnp
import pytest

from dmcr_jax.benchmarks import profile as P

# One worker runs the module: the command's tests profile the same render program,
# compiled once for all of them.
pytestmark = pytest.mark.xdist_group("benchmarks_profile")


def _gpu_trace():
  return [
      {"ph": "M", "pid": 1, "name": "process_name", "args": {"name": "/host:CPU"}},
      {"ph": "M", "pid": 7, "name": "process_name", "args": {"name": "/device:GPU:0"}},
      {"ph": "M", "pid": 7, "tid": 2, "name": "thread_name", "args": {"name": "Stream #13"}},
      # host work is not device time
      {"ph": "X", "pid": 1, "tid": 5, "ts": 0, "dur": 1000.0, "name": "PjitFunction(f)"},
      # two launches of one fusion (two kernels of one op), one convolution
      {"ph": "X", "pid": 7, "tid": 2, "ts": 0, "dur": 30.0, "name": "loop_fusion_kernel",
       "args": {"hlo_op": "fusion.3", "hlo_module": "jit_f"}},
      {"ph": "X", "pid": 7, "tid": 2, "ts": 40, "dur": 10.0, "name": "loop_fusion_kernel",
       "args": {"hlo_op": "fusion.3", "hlo_module": "jit_f"}},
      {"ph": "X", "pid": 7, "tid": 2, "ts": 60, "dur": 60.0, "name": "sm90_xmma_fprop",
       "args": {"hlo_op": "convolution.1", "hlo_module": "jit_f"}},
      {"ph": "i", "pid": 7, "tid": 2, "ts": 70, "name": "marker"},
  ]


def test_device_events_are_grouped_per_op_and_per_kernel():
  s = P.summarise(_gpu_trace(), by="op")
  assert s["source"] == "device" and s["total_ms"] == pytest.approx(0.1)
  assert [(r["name"], r["calls"]) for r in s["rows"]] == [("convolution.1", 1), ("fusion.3", 2)]
  conv, fusion = s["rows"]
  assert conv["share"] == pytest.approx(0.6) and fusion["share"] == pytest.approx(0.4)
  assert fusion["mean_us"] == pytest.approx(20.0) and fusion["total_ms"] == pytest.approx(0.04)
  by_kernel = P.summarise(_gpu_trace(), by="kernel", top=1)
  assert [r["name"] for r in by_kernel["rows"]] == ["sm90_xmma_fprop"] and by_kernel["groups"] == 2
  table = P.markdown(s, "title")
  assert table.startswith("title") and "| `convolution.1` | 1 | 0.06 | 60.0 | 60.0% |" in table
  by_category = P.summarise(_gpu_trace(), by="category")
  assert [r["name"] for r in by_category["rows"]] == ["convolution", "fusion"]
  with pytest.raises(ValueError, match="op, category, kernel"):
    P.summarise(_gpu_trace(), by="name")


def test_a_cpu_trace_falls_back_to_xla_threads(tmp_path):
  f = jax.jit(lambda x: jnp.sin(x @ x).sum())
  x = jnp.ones((64, 64))
  jax.block_until_ready(f(x))
  path = P.profile_call(lambda: f(x), str(tmp_path), calls=2)
  assert path.endswith("perfetto_trace.json.gz") and os.path.exists(path)
  s = P.summarise(P.load_trace(path))
  assert s["source"] == "host threads" and s["rows"] and s["total_ms"] > 0
  assert not any(r["name"].startswith(P.HOST_WRAPPER_PREFIXES) for r in s["rows"])
  # plain JSON traces load too
  plain = tmp_path / "t.json"
  with gzip.open(path, "rt") as src, open(plain, "w") as dst:
    dst.write(src.read())
  assert len(P.load_trace(str(plain))) == len(P.load_trace(path))


@pytest.mark.slow
def test_command_profiles_the_renderer(tmp_path, capsys, monkeypatch):
  monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))  # restored after
  P.main(["render", "--task", "pendulum-swingup", "--batch", "2", "--size", "16",
          "--calls", "1", "--top", "5", "--out", str(tmp_path)])
  summary = json.loads((tmp_path / "summary.json").read_text())
  assert summary["workload"].startswith("render_batch, pendulum-swingup, N = 2")
  assert 0 < len(summary["rows"]) <= 5 and summary["compile_s"] > 0
  assert (tmp_path / summary["trace"]).exists()
  assert "| op / kernel |" in (tmp_path / "summary.md").read_text()
  assert "Traced time on the host threads" in capsys.readouterr().out
  assert "--xla_gpu_enable_command_buffer=" in os.environ["XLA_FLAGS"]


@pytest.mark.slow
def test_command_can_leave_only_the_summary(tmp_path, monkeypatch):
  monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))  # restored after
  P.main(["render", "--task", "pendulum-swingup", "--batch", "2", "--size", "16",
          "--calls", "1", "--top", "5", "--out", str(tmp_path), "--no-keep-trace"])
  assert sorted(os.listdir(tmp_path)) == ["summary.json", "summary.md"]
  summary = json.loads((tmp_path / "summary.json").read_text())
  assert summary["trace"] is None and summary["rows"]
  elsewhere = tmp_path / "traces"
  P.main(["render", "--task", "pendulum-swingup", "--batch", "2", "--size", "16",
          "--calls", "1", "--out", str(tmp_path / "out"), "--trace-dir", str(elsewhere)])
  assert sorted(os.listdir(tmp_path / "out")) == ["summary.json", "summary.md"]
  trace = json.loads((tmp_path / "out" / "summary.json").read_text())["trace"]
  assert trace.startswith(str(elsewhere)) and os.path.exists(trace)


def test_command_rejects_bad_arguments(tmp_path, capsys):
  with pytest.raises(SystemExit):
    P.main(["render", "--batch", "0", "--out", str(tmp_path)])
  assert "--batch must be positive, got 0" in capsys.readouterr().err
  with pytest.raises(SystemExit):
    P.main(["learner", "--by", "name", "--out", str(tmp_path)])
  assert "invalid choice: 'name'" in capsys.readouterr().err
  with pytest.raises(SystemExit):
    P.main(["learner", "--agents", "0", "--out", str(tmp_path)])
  assert "--agents must be positive, got 0" in capsys.readouterr().err
  with pytest.raises(SystemExit):
    P.main(["learner", "--agent-loop", "scan", "--out", str(tmp_path)])
  assert "--agent-loop must be one of vmap, map, got 'scan'" in capsys.readouterr().err


def _inner(x):
  return jnp.sin(x) * jnp.cos(x)  # the op whose source the labels must name


def _outer(x):
  return _inner(x) + 1.0


def test_hlo_sources_name_the_python_lines_of_compiled_ops():
  import inspect
  text = jax.jit(_outer).lower(jnp.ones((64,))).compile().as_text()
  sources = {k: v for k, v in P.hlo_sources(text).items() if k != "fusion.3"}
  inner_line = inspect.getsourcelines(_inner)[1] + 1
  outer_line = inspect.getsourcelines(_outer)[1] + 1
  labels = set(sources.values())
  assert any(lab.startswith(f"test_benchmarks_profile.py:{inner_line} _inner ← {outer_line} _outer")
             for lab in labels), labels
  # grouping a trace by source: ops it knows get their label, the rest say so
  op = next(n for n, lab in sources.items() if lab.startswith("test_benchmarks_profile.py"))
  events = _gpu_trace() + [{"ph": "X", "pid": 7, "tid": 2, "ts": 200, "dur": 5.0,
                            "name": "k", "args": {"hlo_op": op}}]
  rows = {r["name"]: r for r in P.summarise(events, by="source", sources=sources)["rows"]}
  assert rows[sources[op]]["calls"] == 1
  assert rows["fusion.3 (no source)"]["calls"] == 2
