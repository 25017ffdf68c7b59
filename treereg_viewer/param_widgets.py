"""GUI inputs for one parameter section, built from the field metadata in treereg_core.params.

Each field's type picks the input (checkbox, dropdown for `choices`, text for numbers, optional
values and lists); its label carries the unit and its hint the one-line doc and range.
A change is handed to `on_change(section, name, value)`, which returns None when accepted or a
message when rejected; a rejected value is put back so the input always shows what is in force.

Numbers are typed into text inputs, not viser's number inputs: those drop every character that is
not a digit, so "1e12" arrives as 112 and "1e-3" as 13. The text is checked by the parameter tree
(`Params.with_value`), the one place that checks a value (range, type, finiteness), as for the
command line and config files. A text input reports every keystroke, so a typed value is applied
once the input has been still for `SETTLE_S` (or at once when Run is pressed: `flush`).
"""

from __future__ import annotations

import dataclasses
import threading
import types
import typing
from typing import Any, Callable

import viser
from viser import _messages

from treereg_core import params as P

#: on_change(section, field name, raw value) -> None if accepted, else the reason it was rejected.
OnChange = Callable[[str, str, Any], "str | None"]

#: A typed value is applied when its input has been still this long (seconds).
SETTLE_S = 0.8

_SUFFIXES = ("_deg", "_m", "_px")


def field_label(fld: dataclasses.Field) -> str:
    """'inlier_m' -> 'inlier (m)'; 'orb_nfeatures' -> 'orb nfeatures'."""
    name = fld.name
    for s in _SUFFIXES:
        if name.endswith(s):
            name = name[: -len(s)]
            break
    unit = fld.metadata.get("unit") or ""
    text = name.replace("_", " ")
    # "min points", not "min points (points)": a unit the name already says is not repeated.
    return f"{text} ({unit})" if unit and unit not in text.split() else text


def field_hint(fld: dataclasses.Field) -> str:
    meta = fld.metadata
    parts = [meta.get("doc") or ""]
    lo, hi = meta.get("min"), meta.get("max")
    if lo is not None or hi is not None:
        parts.append(f"range [{'' if lo is None else lo}, {'' if hi is None else hi}]")
    return "; ".join(p for p in parts if p)


def _hint_type(section: str, fld: dataclasses.Field) -> tuple[Any, bool]:
    """The field's annotated type without Optional, and whether None is allowed."""
    cls = type(getattr(P.Params(), section))
    hint = typing.get_type_hints(cls)[fld.name]
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in args:
        return next(a for a in args if a is not type(None)), True
    return hint, False


def format_text(value: Any) -> str:
    """How a text input shows a value: None -> '', 0.001 -> '0.001', tuples -> '0.25, 0.5, 0.75'."""
    if value is None:
        return ""
    if isinstance(value, tuple):
        return ", ".join(format_text(v) for v in value)
    if isinstance(value, float):
        short = f"{value:g}"
        return short if float(short) == value else repr(value)
    return str(value)


class SectionWidgets:
    """The inputs of one parameter section, in field order, in the current GUI container."""

    def __init__(self, gui: viser.GuiApi, section: str, params: P.Params, on_change: OnChange) -> None:
        self.section = section
        self._on_change = on_change
        self._syncing = threading.local()
        self._timers: dict[str, threading.Timer] = {}
        self._timers_lock = threading.Lock()
        self.handles: dict[str, Any] = {}
        self._kinds: dict[str, str] = {}
        self._choices: dict[str, tuple[Any, ...]] = {}
        sec = getattr(params, section)
        for fld in P.field_info(section):
            self._add(gui, fld, getattr(sec, fld.name))

    def _add(self, gui: viser.GuiApi, fld: dataclasses.Field, value: Any) -> None:
        meta = fld.metadata
        label, hint = field_label(fld), field_hint(fld)
        typ, optional = _hint_type(self.section, fld)
        choices = meta.get("choices")
        if typ is bool and not optional:
            h = gui.add_checkbox(label, bool(value), hint=hint)
            kind = "bool"
        elif choices is not None and not optional:
            self._choices[fld.name] = tuple(choices)
            h = gui.add_dropdown(label, [str(c) for c in choices], initial_value=str(value), hint=hint)
            kind = "choice"
        else:
            extra = " Leave empty for none." if optional else ""
            if typing.get_origin(typ) is tuple:
                extra += " Values separated by commas." + (" One value means the same for both." if
                                                           len(set(typing.get_args(typ))) == 1 and len(typing.get_args(typ)) == 2 else "")
            h = gui.add_text(label, format_text(value), hint=hint + "." + extra if hint else extra.strip())
            kind = "text"
        self.handles[fld.name] = h
        self._kinds[fld.name] = kind
        # Keystrokes come from a browser (a client); a value set in Python is complete at once.
        h.on_update(lambda event, name=fld.name: self._changed(name, typed=event.client is not None))

    def _changed(self, name: str, typed: bool = False) -> None:
        if getattr(self._syncing, "on", False):
            return
        if self._kinds[name] != "text" or not typed:
            self._apply(name)
            return
        with self._timers_lock:  # typing: apply once the input is still
            old = self._timers.pop(name, None)
            if old is not None:
                old.cancel()
            timer = threading.Timer(SETTLE_S, self._settled, args=(name,))
            timer.daemon = True
            self._timers[name] = timer
        timer.start()

    def _settled(self, name: str) -> None:
        with self._timers_lock:
            if self._timers.get(name) is not threading.current_thread():
                return  # a newer keystroke, or a flush, took over
            del self._timers[name]
        self._apply(name)

    def flush(self) -> None:
        """Apply typed values still waiting to settle (Run was pressed right after typing)."""
        with self._timers_lock:
            waiting = list(self._timers)
            for timer in self._timers.values():
                timer.cancel()
            self._timers.clear()
        for name in waiting:
            self._apply(name)

    def _apply(self, name: str) -> None:
        h = self.handles[name]
        kind = self._kinds[name]
        value: Any = h.value
        if kind == "choice":
            value = next((c for c in self._choices[name] if str(c) == value), value)
        elif kind == "text":
            value = value.strip() or None
        self._on_change(self.section, name, value)

    def sync(self, params: P.Params) -> None:
        """Show `params` in the inputs without reporting them as changes (a load, a preset, a revert)."""
        sec = getattr(params, self.section)
        with self._timers_lock:
            typing = set(self._timers)  # a value still being typed is not overwritten
        self._syncing.on = True
        try:
            for name, h in self.handles.items():
                if name in typing:
                    continue
                v = getattr(sec, name)
                kind = self._kinds[name]
                shown = str(v) if kind == "choice" else format_text(v) if kind == "text" else v
                if h.value != shown:
                    h.value = shown
        finally:
            self._syncing.on = False

    def set_disabled(self, on: bool) -> None:
        """Grey the inputs out (a tab following the presenter: its parameters are the presenter's)."""
        for h in self.handles.values():
            if h.disabled != on:
                h.disabled = on

    def show_in_force(self, name: str, params: P.Params) -> None:
        """After a value was applied: the input shows the value in force, sent to the tab even when the
        server's copy of the input already holds it. With two tabs, a keystroke in one can cross the
        other tab's change on its way in: the browser then shows the other tab's value while the
        server's copy (and, once applied, the parameters) hold the keystroke's."""
        with self._timers_lock:
            if name in self._timers:  # typed on since: that value is applied next
                return
        h = self.handles[name]
        v = getattr(getattr(params, self.section), name)
        kind = self._kinds[name]
        shown = str(v) if kind == "choice" else format_text(v) if kind == "text" else v
        if h.value != shown:  # e.g. "1e1" typed, 10 in force
            self._syncing.on = True
            try:
                h.value = shown
            finally:
                self._syncing.on = False
            return
        impl = h._impl  # viser sends only changes: re-send the value as it is
        impl.gui_api._websock_interface.queue_message(_messages.GuiUpdateMessage(impl.uuid, {"value": shown}))
