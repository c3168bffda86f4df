"""The README's and the docs' Python snippets run as written, and their links resolve.

Every ```python block of README.md and docs/*.md is one case. The fast test compiles
each block (Python syntax); the slow one runs it in a fresh interpreter (a subprocess
whose working directory is a temporary folder, with the repository on PYTHONPATH so
that `examples.augmentations` imports) at tiny sizes: the batch sizes the snippets use
for show, `TINY_SIZES` (1,024, 4,096 and 256 envs, looks or actions), are replaced
textually by 4, and nothing else changes. A block must therefore be self-contained
(its imports, its inputs); one not meant to run (a signature, printed output, a shell
command) must not be fenced as python. A relative link or image of those pages must
name a file of the repository.
"""

import os
import re
import subprocess
import sys

import pytest

# Snippets that compile the same programs (the README's walker task and pool env and
# docs/tasks.md's and docs/envs.md's; the protocol passes of docs/protocol.md; the
# cartpole ray-caster envs) share an xdist group: one worker runs them one after
# another, so that each loads the others' compiled programs from the session's
# compilation cache instead of compiling them side by side. The groups themselves run
# on whichever worker is free.
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


BLOCKS = python_blocks()
IDS = [where for where, _ in BLOCKS]
RUNS = [pytest.param(where, code, id=where, marks=pytest.mark.xdist_group(group(code)))
        for where, code in BLOCKS]


def test_there_are_snippets_and_no_stray_fences():
  assert len(BLOCKS) >= 8, IDS
  for page in pages():
    with open(os.path.join(ROOT, page)) as f:
      fences = [l for l in f.read().splitlines() if l.startswith("```")]
    assert len(fences) % 2 == 0, f"{page}: an unclosed ``` fence"


@pytest.mark.parametrize("where, code", BLOCKS, ids=IDS)
def test_snippet_compiles(where, code):
  compile(code, where, "exec")


@pytest.mark.slow
@pytest.mark.parametrize("where, code", RUNS)
def test_snippet_runs_at_tiny_sizes(where, code, tmp_path):
  env = dict(os.environ, PYTHONPATH=os.pathsep.join(
      p for p in (ROOT, os.environ.get("PYTHONPATH")) if p))
  out = subprocess.run([sys.executable, "-c", TINY_SIZES.sub("4", code)], cwd=tmp_path,
                       env=env, capture_output=True, text=True, timeout=900)
  assert out.returncode == 0, f"{where} failed:\n{out.stderr[-3000:]}"


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
