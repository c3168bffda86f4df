"""The README's and the docs' Python snippets run as written, and their links resolve.

Every ```python block of README.md and docs/*.md is one case. The fast test compiles
each block (Python syntax); the slow one runs it at tiny sizes in a snippet runner: a
separate interpreter (with the repository on PYTHONPATH so that
`examples.augmentations` imports) that runs each block it is sent as a script of its
own, with fresh globals named `__main__`, in the test's temporary folder as working
directory. One runner serves the snippets of a test process one after another, so
that they share its imports and its in-memory compilations; a block must still be
self-contained (its own imports and inputs), as its globals start empty. Tiny sizes:
the batch sizes the snippets use for show, `TINY_SIZES` (1,024, 4,096 and 256 envs,
looks or actions), are replaced textually by 4, and the image sizes `IMAGE_SIZES`
(64 and 84 px) by 16; nothing else changes. A block identical to an earlier one up to
comments and spacing is run once, as the earlier one. A block not meant to run (a
signature, printed output, a shell command) must not be fenced as python. A relative
link or image of those pages must name a file of the repository.
"""

import io
import json
import os
import re
import select
import subprocess
import sys
import tokenize

import pytest

# Snippets that compile the same programs (the README's walker task and pool env and
# docs/tasks.md's and docs/envs.md's; the protocol passes of docs/protocol.md; the
# cartpole ray-caster envs) share an xdist group: one worker runs them one after
# another in its snippet runner, so that each reuses the others' compiled programs (in
# the runner's memory, or from the session's compilation cache) instead of compiling
# them side by side. The groups themselves run on whichever worker is free.
def group(code: str) -> str:
  """The xdist group of a snippet: by the programs it compiles."""
  if "protocol." in code:
    return "readme-protocol"
  if "loop.train" in code:
    return "readme-train"
  if "walker-walk" in code:
    return "readme-walker"
  if "cartpole" in code:
    return "readme-cartpole"
  return "readme"

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TINY_SIZES = re.compile(r"\b(1024|4096|256)\b")
IMAGE_SIZES = re.compile(r"\b(64|84)\b")


def tiny(code: str) -> str:
  """`code` at tiny sizes: `TINY_SIZES` replaced by 4, `IMAGE_SIZES` by 16."""
  return IMAGE_SIZES.sub("16", TINY_SIZES.sub("4", code))


def pages() -> list[str]:
  """README.md and every docs/*.md, as paths relative to the repository."""
  docs = sorted(f"docs/{f}" for f in os.listdir(os.path.join(ROOT, "docs")) if f.endswith(".md"))
  return ["README.md"] + docs


def python_blocks() -> list[tuple[str, str]]:
  """(`page:line`, code) of every ```python block of `pages()`."""
  blocks = []
  for page in pages():
    with open(os.path.join(ROOT, page)) as f:
      text = f.read()
    for m in re.finditer(r"^```python\n(.*?)^```", text, re.S | re.M):
      blocks.append((f"{page}:{text.count(chr(10), 0, m.start()) + 1}", m.group(1)))
  return blocks


def tokens(code: str) -> tuple[str, ...]:
  """The Python tokens of `code` without its comments, spacing and line breaks: two
  blocks with the same tokens run the same program."""
  skip = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT,
          tokenize.DEDENT, tokenize.ENDMARKER}
  return tuple(t.string for t in tokenize.generate_tokens(io.StringIO(code).readline)
               if t.type not in skip)


def distinct(blocks: list[tuple[str, str]]) -> list[tuple[str, str]]:
  """`blocks` without those whose `tokens` an earlier block has."""
  seen, kept = set(), []
  for where, code in blocks:
    if tokens(code) not in seen:
      seen.add(tokens(code))
      kept.append((where, code))
  return kept


BLOCKS = python_blocks()
IDS = [where for where, _ in BLOCKS]
# By group, so that a test process runs a group's snippets one after another.
RUNS = [pytest.param(where, code, id=where, marks=pytest.mark.xdist_group(group(code)))
        for where, code in sorted(distinct(BLOCKS), key=lambda block: group(block[1]))]

# The snippet runner: reads one JSON request a line from stdin ({"code", "where",
# "cwd", "clear"}), runs the code as a script of its own (fresh globals, `cwd` as
# working directory), and answers one JSON line ({"ok", "error"}) on the stdout it
# started with; the snippets' own output (Python's and C libraries') goes to stderr,
# and their stdin is empty.
RUNNER = r"""
import json, os, sys, traceback
answers, requests = os.fdopen(os.dup(1), "w"), sys.stdin
os.dup2(2, 1)
sys.stdout, sys.stdin = sys.stderr, open(os.devnull)
for line in requests:
  request = json.loads(line)
  if request["clear"] and "jax" in sys.modules:
    sys.modules["jax"].clear_caches()
  os.chdir(request["cwd"])
  error = None
  try:
    exec(compile(request["code"], request["where"], "exec"), {"__name__": "__main__"})
  except BaseException:
    error = traceback.format_exc()
  sys.stderr.flush()
  answers.write(json.dumps({"ok": error is None, "error": error}) + "\n")
  answers.flush()
"""
RUN_S = 900   # one snippet, compiling on a busy 2-core machine


class SnippetRunner:
  """A `RUNNER` process, started on first use and again after one died; its stderr
  is a file in `folder`. `run(where, code, cwd, group)` runs one snippet and returns
  None or its error (the traceback and the end of its output); the runner drops its
  in-memory compilations when the xdist group changes, as conftest does between
  groups."""

  def __init__(self, folder):
    self.folder, self.proc, self.group = folder, None, None

  def _start(self):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (ROOT, os.environ.get("PYTHONPATH")) if p))
    self.log = open(os.path.join(self.folder, f"runner-{len(os.listdir(self.folder))}.log"),
                    "w+")
    self.proc = subprocess.Popen([sys.executable, "-c", RUNNER], stdin=subprocess.PIPE,
                                 stdout=subprocess.PIPE, stderr=self.log, text=True, env=env)

  def run(self, where: str, code: str, cwd: str, group: str) -> str | None:
    if self.proc is None or self.proc.poll() is not None:
      self._start()
    start = self.log.seek(0, os.SEEK_END)
    self.proc.stdin.write(json.dumps(dict(where=where, code=code, cwd=cwd,
                                          clear=group != self.group)) + "\n")
    self.proc.stdin.flush()
    self.group = group
    ready, _, _ = select.select([self.proc.stdout], [], [], RUN_S)
    line = self.proc.stdout.readline() if ready else ""
    self.log.seek(start)
    output = self.log.read()[-3000:]
    if not line:
      self.close()
      return f"the runner {'died' if ready else f'took over {RUN_S} s'}:\n{output}"
    answer = json.loads(line)
    return None if answer["ok"] else f"{answer['error']}\n{output}"

  def close(self):
    if self.proc is not None:
      self.proc.kill()
      self.proc.wait()
      self.proc = None
      self.log.close()


@pytest.fixture(scope="module")
def runner(tmp_path_factory):
  """The module's `SnippetRunner`."""
  r = SnippetRunner(str(tmp_path_factory.mktemp("snippet-runner")))
  yield r
  r.close()


def test_there_are_snippets_and_no_stray_fences():
  assert len(BLOCKS) >= 8, IDS
  for page in pages():
    with open(os.path.join(ROOT, page)) as f:
      fences = [l for l in f.read().splitlines() if l.startswith("```")]
    assert len(fences) % 2 == 0, f"{page}: an unclosed ``` fence"


def test_the_runs_cover_every_block_once():
  runs = {where for where, _ in distinct(BLOCKS)}
  assert len({tokens(c) for _, c in BLOCKS}) == len(runs)
  for where, code in BLOCKS:
    assert where in runs or any(tokens(code) == tokens(c) for w, c in BLOCKS if w in runs)
  assert tokens("x = f(1,  2)  # one\n") == tokens("x = f(1, 2)\n") != tokens("x = f(1, 3)")


@pytest.mark.parametrize("where, code", BLOCKS, ids=IDS)
def test_snippet_compiles(where, code):
  compile(code, where, "exec")


def test_the_runner_runs_each_snippet_apart_and_reports_its_error(runner, tmp_path):
  assert runner.run("a", "x = 1\nopen('made', 'w').close()", str(tmp_path), "readme") is None
  assert (tmp_path / "made").exists()
  error = runner.run("b", "print('shown')\nx", str(tmp_path), "readme")   # fresh globals
  assert "NameError: name 'x' is not defined" in error and "shown" in error
  assert "SystemExit: 3" in runner.run("c", "import sys; sys.exit(3)", str(tmp_path), "readme")
  assert "died" in runner.run("d", "import os; os._exit(0)", str(tmp_path), "readme")
  assert runner.run("e", "import dmcr_jax", str(tmp_path), "readme") is None   # restarted


@pytest.mark.slow
@pytest.mark.parametrize("where, code", RUNS)
def test_snippet_runs_at_tiny_sizes(where, code, tmp_path, runner, request):
  group = request.node.get_closest_marker("xdist_group").args[0]
  error = runner.run(where, tiny(code), str(tmp_path), group)
  assert error is None, f"{where} failed:\n{error}"


def test_relative_links_name_files_of_the_repository():
  missing = []
  for page in pages():
    with open(os.path.join(ROOT, page)) as f:
      text = f.read()
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
      if re.match(r"[a-z]+:", target) or target.startswith("#"):
        continue
      path = os.path.normpath(os.path.join(os.path.dirname(page), target.split("#")[0]))
      if not os.path.exists(os.path.join(ROOT, path)):
        missing.append(f"{page}: {target}")
  assert not missing, missing
