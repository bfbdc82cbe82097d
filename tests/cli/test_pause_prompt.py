"""A command-line build that pauses says why and how to go on, and takes the answer from its terminal
(controller/cli/pause_prompt.py), against the simulators over the real protocols."""
from __future__ import annotations

import asyncio
import io
from pathlib import Path

import pytest

from controller.defaults import SIM_REPLY_TIMEOUT_MS
from controller.cli.pause_prompt import PausePrompt
from controller.harness.cell import open_cell, with_urls
from core.config import load_cell, load_sim
from tests.jobs import PassSpec, line, small_job

pytestmark = pytest.mark.realtime   # a cell on the wall clock (tests/conftest.py)


async def _paused_build(tmp_path: Path, answer: str) -> tuple[str, list[str], list[str]]:
    job = small_job([[PassSpec(line(12.0, n=3))], [PassSpec(line(12.0, n=3))]])
    cfg = with_urls(load_cell(), {}, time_scale=20)
    said: list[str] = []
    async with open_cell(cfg, sim=load_sim(), log_dir=tmp_path / "log", runs_dir=tmp_path / "runs",
                         reply_timeout_ms=SIM_REPLY_TIMEOUT_MS) as ctl:
        ctl.open_job(job)
        prompt = PausePrompt(ctl, said.append, io.StringIO(answer))
        build = asyncio.ensure_future(ctl.start())
        while ctl.snapshot().state != "running_depositing":
            await asyncio.sleep(0.005)
        ctl.pause()                                   # the operator's pause: at the end of this bead
        res = await asyncio.wait_for(build, 30)
        prompt.close()
    return res.state, said, prompt.answers


async def test_a_paused_build_says_how_to_go_on_and_resumes_on_the_answer(tmp_path: Path) -> None:
    state, said, answers = await _paused_build(tmp_path, "what?\nr\n")
    assert state == "complete" and answers == ["r"]
    assert said[0].startswith("paused: ") and "r + Enter: resume" in said[1] and "cell resume" in said[1]
    assert any("type r (resume) or s (stop)" in s for s in said)   # an unknown answer is asked again


async def test_with_no_terminal_to_answer_the_build_stops_and_says_how_to_resume(tmp_path: Path) -> None:
    state, said, answers = await _paused_build(tmp_path, "")
    assert state == "aborted" and answers == [""]
    assert any("stdin is not a terminal and has ended" in s for s in said)
    assert any(s.startswith("stopping; `cell resume ") for s in said)
