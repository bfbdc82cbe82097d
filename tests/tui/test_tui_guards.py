"""Guarded actions (issue 19): abort asks first, and the quit dialog's default is to stay."""
from __future__ import annotations

from controller.tui.app import CellApp, ConfirmAbort, ConfirmQuit
from controller.tui.replay import ReplaySession
from tests.tui.recorded import recorded_view


async def test_abort_asks_and_enter_keeps_building() -> None:
    session = ReplaySession(recorded_view())
    app = CellApp(session)
    async with app.run_test(size=(120, 36)) as pilot:
        await pilot.press("a")
        await pilot.pause()
        assert isinstance(app.screen, ConfirmAbort) and app.focused.id == "abort-no"
        await pilot.press("enter")  # the default answer: keep building, nothing sent
        await pilot.pause()
        assert not isinstance(app.screen, ConfirmAbort) and "abort" not in session.refused
        await pilot.press("a")
        await pilot.pause()
        await pilot.click("#abort-yes")
        await pilot.pause()
        assert session.refused == ["abort"]  # sent once, after the confirmation


async def test_quit_during_a_build_defaults_to_stay() -> None:
    app = CellApp(ReplaySession(recorded_view()))
    async with app.run_test(size=(120, 36)) as pilot:
        await pilot.press("q")
        await pilot.pause()
        assert isinstance(app.screen, ConfirmQuit) and app.focused.id == "quit-no"
        await pilot.press("enter")
        await pilot.pause()
        assert not isinstance(app.screen, ConfirmQuit) and app.is_running


async def test_question_mark_opens_the_help_with_what_the_state_allows() -> None:
    from controller.tui.help import HelpScreen

    app = CellApp(ReplaySession(recorded_view()))
    async with app.run_test(size=(120, 36)) as pilot:
        await pilot.press("question_mark")
        await pilot.pause()
        assert isinstance(app.screen, HelpScreen)
        text = str(app.screen.query_one("#help-text").render())
        assert "Pause" in text and "allowed now" in text and "Ctrl+E" in text
        await pilot.press("escape")
        await pilot.pause()
        assert not isinstance(app.screen, HelpScreen)
