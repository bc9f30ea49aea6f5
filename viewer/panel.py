"""The editor's panel: a Tk window beside the 3D view with the switches of what is shown, the prior toggle, the
nudge step, the buttons, the PCA sliders of the category and a status line.

:class:`EditorPanel` is a part of :class:`kpd.viewer.app.EditorApp` (its windows are the app's): the widgets are the
app's attributes, their callbacks the app's ``_on_<event>`` methods, and the settings reach them in one place
(:meth:`EditorPanel._apply_settings`).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from kpd.viewer.session import component_offsets

__all__ = ["EditorPanel", "PANEL_WIDTH", "VIEW_LEFT", "VIEW_TOP"]

log = logging.getLogger("kpd.viewer.app")  # the editor's messages, under one name

PANEL_WIDTH = 300  # pixels
VIEW_LEFT, VIEW_TOP = 0, 0  # where the 3D view opens on the screen; the panel opens to its right
_MAX_SLIDERS = 8  # PCA components with a slider


class EditorPanel:
    """The panel of an editor app. The app provides its state (``settings``, ``prior``, ``session``, ``selection``,
    ``rig``, ``mesh``, ``num_keypoints``, ``title``), the actions the buttons and keys call (``_on_undo``,
    ``_on_save``...) and the frame scheduler's ``_count_input`` and ``_changed``
    (:class:`kpd.viewer.scheduler.FrameScheduler`)."""

    def _init_panel(self) -> None:
        self._sigmas = np.zeros(0)  # the PCA sliders' values, in standard deviations
        self._quiet_sliders = False  # set while the sliders are moved back to 0 (no edit then)
        self._message_text = ""

    def _build_panel(self) -> None:
        import tkinter as tk

        from kpd.viewer.glview import NoWindowError

        s = self.settings
        try:
            root = tk.Tk()
        except tk.TclError as exc:
            raise NoWindowError(f"could not open the editor's panel window: {exc}") from exc
        self.root = root
        root.title(f"{self.title} - panel")
        root.geometry(f"+{VIEW_LEFT + s.width + 8}+{VIEW_TOP}")  # beside the 3D view, as tall as its widgets need
        root.protocol("WM_DELETE_WINDOW", self._on_panel_close)
        pad = {"padx": 6, "pady": 1, "anchor": "w"}
        tk.Label(root, text=f"{self.title}\n{self.num_keypoints} keypoints, {len(self.mesh.vertices):,} vertices",
                 justify="left").pack(**pad)
        tk.Label(root, text="Show", font=("TkDefaultFont", 10, "bold")).pack(**pad)
        self._checks: dict[str, Any] = {}
        for name, text in (("show_keypoints", "keypoints"), ("show_labels", "numbers"),
                           ("show_cage", "cage (wireframe)"), ("show_ghost", "original shape (ghost)"),
                           ("xray", "see-through mesh (wireframe)")):
            var = tk.BooleanVar(value=getattr(s, name))
            tk.Checkbutton(root, text=text, variable=var,
                           command=lambda name=name, var=var: self._on_setting(name, bool(var.get()))).pack(**pad)
            self._checks[name] = var
        tk.Label(root, text="Edit", font=("TkDefaultFont", 10, "bold")).pack(**pad)
        var = tk.BooleanVar(value=bool(s.prior and self.prior is not None))
        self.prior_box = tk.Checkbutton(root, text="prior (others follow the category)", variable=var,
                                        command=lambda: self._on_setting("prior", bool(self._checks["prior"].get())),
                                        state="normal" if self.prior is not None else "disabled")
        self.prior_box.pack(**pad)
        self._checks["prior"] = var
        row = tk.Frame(root)
        tk.Label(row, text="nudge step").pack(side="left")
        self.step = tk.Spinbox(row, from_=0.001, to=0.5, increment=0.005, width=7,
                               command=lambda: self._on_step(self.step.get()))
        self.step.delete(0, "end")
        self.step.insert(0, f"{s.nudge_step:g}")
        self.step.bind("<Return>", lambda _e: self._on_step(self.step.get()))
        self.step.pack(side="left")
        row.pack(**pad)
        buttons = [("Undo (U)", self._on_undo), ("Redo (Y)", self._on_redo), ("Reset (R)", self._on_reset),
                   ("Save mesh (S)", self._on_save), ("Save session (J)", self._on_save_session),
                   ("Load session (L)", self._on_load_session), ("Screenshot (P)", self._on_screenshot)]
        for i in range(0, len(buttons), 2):
            row = tk.Frame(root)
            for text, callback in buttons[i:i + 2]:
                tk.Button(row, text=text, width=14, command=lambda c=callback: self._input_then(c)).pack(side="left")
            row.pack(**pad)
        self.sliders: list[Any] = []
        if self.prior is not None:
            count = min(len(self.prior.components_), _MAX_SLIDERS)
            self._sigmas = np.zeros(len(self.prior.components_))
            tk.Label(root, text="Category (PCA, std. dev.)", font=("TkDefaultFont", 10, "bold")).pack(**pad)
            for m in range(count):
                row = tk.Frame(root)
                tk.Label(row, text=f"{m + 1}", width=2).pack(side="left")
                slider = tk.Scale(row, from_=-3.0, to=3.0, resolution=0.01, orient="horizontal", length=230,
                                  showvalue=False, sliderlength=18,
                                  command=lambda value, m=m: self._on_slider(m, float(value)))
                slider.pack(side="left")
                row.pack(**pad)
                self.sliders.append(slider)
        tk.Label(root, justify="left", text="click: select   shift+click: add\n"
                                            "drag a keypoint: move it\n"
                                            "drag elsewhere: orbit   right drag: pan\n"
                                            "wheel: zoom   arrows, PgUp/PgDn: nudge\n"
                                            "U undo  Y redo  R reset  T prior\n"
                                            "S save mesh  J/L session  P shot").pack(**pad)
        self.status = tk.Label(root, text="", justify="left", anchor="w")
        self.status.pack(**pad)
        keys = {"u": self._on_undo, "y": self._on_redo, "r": self._on_reset, "s": self._on_save,
                "j": self._on_save_session, "l": self._on_load_session, "p": self._on_screenshot,
                "t": lambda: self._on_setting("prior", not self.settings.prior), "Escape": self._on_clear}
        for key, action in keys.items():
            root.bind(f"<KeyPress-{key}>", lambda _e, a=action: self._input_then(a))
        root.update()
        self._update_status()

    def _input_then(self, action: Any) -> None:
        """A button or key of the panel: an input like those of the 3D view, then its action."""
        self._count_input("panel")
        action()

    def _on_panel_close(self) -> None:
        self._running = False

    def _apply_settings(self) -> None:
        """The one place where the settings reach the widgets and the scene."""
        s = self.settings
        self.drawing.settings = s
        for name, var in self._checks.items():
            value = bool(s.prior and self.prior is not None) if name == "prior" else bool(getattr(s, name))
            if bool(var.get()) != value:
                var.set(value)
        self._changed(mesh=True)

    def _on_setting(self, name: str, value: Any) -> None:
        if name == "prior" and self.prior is None:
            value = False
        self.settings = self.settings.replace(**{name: value})
        self._apply_settings()
        self._emit("settings", name=name, value=value)

    def _on_step(self, text: str) -> None:
        try:
            value = float(text)
        except ValueError:
            self._message(f"nudge step must be a number; got {text!r}")
            return
        if not (math.isfinite(value) and value > 0):
            self._message(f"nudge step must be positive; got {text!r}")
            return
        self._on_setting("nudge_step", value)

    def _update_status(self) -> None:
        prior = "on" if self.settings.prior and self.prior is not None else "off"
        if self.session is None:
            text = "binding the mesh to the model...\n(keypoints appear when it is done)"
        else:
            text = (f"selected: {', '.join(map(str, self.selection)) or '-'}\n"
                    f"moved: {len(self.session.moved)}   undo: {self.session.depth}   prior: {prior}")
        if self._message_text:
            text += "\n" + self._message_text
        if hasattr(self, "status"):
            self.status.configure(text=text)

    def _message(self, text: str) -> None:
        log.info("%s", text)
        self._message_text = text
        self._update_status()

    def _reset_sliders(self) -> None:
        self._sigmas[:] = 0.0
        self._quiet_sliders = True
        try:
            for slider in self.sliders:
                if float(slider.get()) != 0.0:
                    slider.set(0.0)
            if self.sliders:
                self.root.update_idletasks()
        finally:
            self._quiet_sliders = False

    def _on_slider(self, m: int, value: float) -> None:
        if self._quiet_sliders or self.prior is None or value == self._sigmas[m] or not self._bound():
            return
        self._count_input("slider", component=m, value=value)
        self._sigmas[m] = float(value)
        keypoints = self._slider_base + component_offsets(self.prior, self.rig.normalizer, self._sigmas)
        if self.session.apply(keypoints, label="component", merge=("component", m)):
            self._changed()
        self._emit("component", component=m, value=float(value))
