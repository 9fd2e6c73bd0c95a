"""Stage 15a — the interactive preview window (glfw + moderngl): orbit and walk-through, modes, exposure,
relighting, screenshots.

The interaction lives in :class:`ViewerState` (pure Python/numpy: keys are names such as ``"w"``, ``"tab"``,
``"f12"``), so it is tested without a display; :func:`run_window` is a thin glfw shell around it that draws with
:class:`viewers.preview.PreviewRenderer`. glfw is an optional dependency (``pip install glfw``, a self-contained
wheel; ``scripts/setup.sh`` installs it) and needs a display (X11 or Wayland; ``xvfb-run -a`` on a server).

Keys (also printed by ``h``):

=============  ====================================================================
1 … 6 / m      mode: lit, albedo, roughness, metallic, normals, semantics / next mode
tab            switch orbit ↔ walk
mouse          orbit: left-drag rotate, right-drag pan, wheel zoom; walk: left-drag look, wheel speed
w a s d q e    walk: forward, left, back, right, down, up (held)
+ / - / 0      exposure +½ stop / −½ stop / reset
l              next light (the asset's SH, then each --sh / --probe given)
[ / ]          rotate the light −15° / +15° about the world's up axis (+z)
p or f12       screenshot: PNG of the current view (same renderer as ``--headless``)
r              reset the camera;  h  help;  escape  quit
=============  ====================================================================
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from toolkit._checks import DarsError
from toolkit.pinhole import PinholeCamera

from .camera import OrbitController, WalkController, default_camera
from .preview import MODES, PreviewConfig

__all__ = ["ViewerState", "run_window", "HELP"]

HELP = __doc__.split("Keys (also printed by ``h``):", 1)[1].strip()


@dataclass
class ViewerState:
    """Everything the window shows, changed by key and mouse events (no GL, no window).

    Args:
        home: the initial camera (its intrinsics set the vertical field of view).
        target: orbit centre, world (+z up).
        lights: ``(name, sh [9, 3])`` to cycle through; the first is shown first.
        cfg: initial mode / exposure / background.
        speed: walk speed in metres per second.
    """

    home: PinholeCamera
    target: np.ndarray
    lights: list[tuple[str, np.ndarray]]
    cfg: PreviewConfig = field(default_factory=PreviewConfig)
    speed: float = 1.0
    navigation: str = "orbit"
    light_index: int = 0
    light_rotation: float = 0.0
    screenshot_requested: bool = False
    quit_requested: bool = False
    messages: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.lights:
            raise DarsError("ViewerState needs at least one light")
        self.reset_camera()

    # ---------------------------------------------------------------------------------------------- camera
    def reset_camera(self) -> None:
        self.orbit = OrbitController.from_camera(self.home, self.target)
        self.walk = WalkController.from_camera(self.home, self.speed)

    def camera(self, width: int, height: int) -> PinholeCamera:
        """The current view at a framebuffer size (square pixels, the home camera's vertical field of view)."""
        fov_y = 2.0 * math.atan(0.5 * self.home.height / self.home.fy)
        f = 0.5 * height / math.tan(0.5 * fov_y)
        c2w = self.orbit.c2w() if self.navigation == "orbit" else self.walk.c2w()
        return PinholeCamera(c2w, f, f, width / 2, height / 2, width, height, self.home.near, self.home.far)

    # ---------------------------------------------------------------------------------------------- lighting
    def current_sh(self) -> np.ndarray:
        """float64 [9, 3]: the selected light rotated by ``light_rotation`` degrees about +z."""
        import torch

        from toolkit.sh import rotate_sh, rotation_z

        name, sh = self.lights[self.light_index]
        if self.light_rotation % 360.0 == 0.0:
            return np.asarray(sh, dtype=np.float64)
        return rotate_sh(torch.as_tensor(np.asarray(sh, dtype=np.float64)), rotation_z(self.light_rotation)).numpy()

    # ---------------------------------------------------------------------------------------------- events
    def _say(self, msg: str) -> str:
        self.messages.append(msg)
        return msg

    def handle_key(self, key: str) -> str | None:
        """Apply a key press (lower-case name: ``"1"``, ``"m"``, ``"tab"``, ``"+"``, ``"f12"`` …).

        Returns:
            a one-line description of what changed, or None for keys without an action.
        """
        key = key.lower()
        if key in "123456" and len(key) == 1:
            self.cfg = replace(self.cfg, mode=MODES[int(key) - 1])
            return self._say(f"mode {self.cfg.mode}")
        if key == "m":
            self.cfg = replace(self.cfg, mode=MODES[(MODES.index(self.cfg.mode) + 1) % len(MODES)])
            return self._say(f"mode {self.cfg.mode}")
        if key == "tab":
            if self.navigation == "orbit":
                self.walk = WalkController.from_camera(self.camera(self.home.width, self.home.height), self.walk.speed)
                self.navigation = "walk"
            else:
                cam = self.camera(self.home.width, self.home.height)
                self.orbit = OrbitController.from_camera(cam, cam.position - cam.c2w[:3, 2] * self.orbit.distance)
                self.navigation = "orbit"
            return self._say(f"navigation {self.navigation}")
        if key in ("+", "=", "kp_add"):
            self.cfg = replace(self.cfg, exposure=self.cfg.exposure + 0.5)
            return self._say(f"exposure {self.cfg.exposure:+.1f} EV")
        if key in ("-", "kp_subtract"):
            self.cfg = replace(self.cfg, exposure=self.cfg.exposure - 0.5)
            return self._say(f"exposure {self.cfg.exposure:+.1f} EV")
        if key == "0":
            self.cfg = replace(self.cfg, exposure=0.0)
            return self._say("exposure 0 EV")
        if key == "l":
            self.light_index = (self.light_index + 1) % len(self.lights)
            return self._say(f"light {self.lights[self.light_index][0]}")
        if key in ("[", "]"):
            self.light_rotation = (self.light_rotation + (15.0 if key == "]" else -15.0)) % 360.0
            return self._say(f"light rotated {self.light_rotation:.0f}°")
        if key in ("p", "f12"):
            self.screenshot_requested = True
            return self._say("screenshot")
        if key == "r":
            self.reset_camera()
            return self._say("camera reset")
        if key == "h":
            return self._say(HELP)
        if key == "escape":
            self.quit_requested = True
            return self._say("quit")
        return None

    def handle_drag(self, dx: float, dy: float, button: str = "left") -> None:
        """Mouse drag by (dx, dy) pixels (y down) with ``left`` or ``right`` held."""
        if self.navigation == "orbit":
            if button == "left":
                self.orbit.rotate(-dx * 0.3, dy * 0.3)
            else:
                self.orbit.pan(-dx * 0.002, dy * 0.002)
        else:
            self.walk.look(dx * 0.2, -dy * 0.2)

    def handle_scroll(self, dy: float) -> None:
        if self.navigation == "orbit":
            self.orbit.zoom(0.9 ** dy)
        else:
            self.walk.speed = float(np.clip(self.walk.speed * 1.25 ** dy, 0.05, 100.0))

    def update(self, seconds: float, held: set[str]) -> None:
        """Advance the walk by the held movement keys over ``seconds``."""
        if self.navigation != "walk":
            return
        fwd = ("w" in held) - ("s" in held)
        right = ("d" in held) - ("a" in held)
        up = ("e" in held) - ("q" in held)
        if fwd or right or up:
            self.walk.move(fwd, right, up, seconds)


_NAMED_KEYS = {"TAB": "tab", "ESCAPE": "escape", "F12": "f12", "KP_ADD": "kp_add", "KP_SUBTRACT": "kp_subtract",
               "EQUAL": "=", "MINUS": "-", "LEFT_BRACKET": "[", "RIGHT_BRACKET": "]"}


def _key_name(glfw, key: int) -> str | None:
    for const, name in _NAMED_KEYS.items():
        if key == getattr(glfw, f"KEY_{const}"):
            return name
    if glfw.KEY_0 <= key <= glfw.KEY_9:
        return str(key - glfw.KEY_0)
    if glfw.KEY_A <= key <= glfw.KEY_Z:
        return chr(ord("a") + key - glfw.KEY_A)
    return None


def run_window(asset, lights: list[tuple[str, np.ndarray]], camera: PinholeCamera | None = None,
               cfg: PreviewConfig = PreviewConfig(), width: int = 1280, height: int = 720,
               screenshot_dir: str | Path = ".", max_frames: int | None = None, keys: tuple[str, ...] = (),
               log=print) -> list[Path]:
    """Open the interactive preview window and run until closed (or ``max_frames`` frames have been drawn).

    Args:
        asset: a loaded GLB (:func:`export.gltf.load_glb`).
        lights: ``(name, sh [9, 3])`` light choices (``l`` cycles).
        camera: the home view (default: framing the asset).
        cfg: initial mode / exposure.
        width, height: window size in screen coordinates.
        screenshot_dir: where ``p`` / ``f12`` write ``dars_view_<time>.png``.
        max_frames: stop after this many frames (tests; None = until the window closes).
        keys: key names applied before the first frame, as if pressed (scripted demos and tests).
        log: where status lines go.

    Returns:
        the screenshots written.

    Raises:
        DarsError: glfw missing, no display, or no OpenGL 3.3 context.
    """
    try:
        import glfw
    except ImportError as e:
        raise DarsError("the preview window needs glfw: `pip install glfw` (or run `dars view ASSET --headless "
                        "--out x.png` without a window)") from e
    import moderngl

    from toolkit.io import write_png

    from .preview import OffscreenPreview, PreviewRenderer

    if not glfw.init():
        raise DarsError("glfw could not initialise a display (no X11/Wayland session?); use `dars view ASSET "
                        "--headless --out x.png`, or run under `xvfb-run -a`")
    written: list[Path] = []
    try:
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        glfw.window_hint(glfw.SAMPLES, 4)
        window = glfw.create_window(width, height, "dars view", None, None)
        if not window:
            raise DarsError("glfw could not open an OpenGL 3.3 core window on this display")
        glfw.make_context_current(window)
        glfw.swap_interval(1)
        ctx = moderngl.create_context()
        home = camera if camera is not None else default_camera(asset.vertices, width, height)
        target = (asset.vertices.min(0) + asset.vertices.max(0)) / 2.0
        if camera is not None:  # orbit around the point the camera looks at, at the asset's centre depth
            depth = float(np.dot(target - camera.position, -camera.c2w[:3, 2]))
            target = camera.position - camera.c2w[:3, 2] * max(depth, 1e-2)
        state = ViewerState(home, np.asarray(target, dtype=np.float64), lights, cfg,
                            speed=max(float(np.ptp(asset.vertices, axis=0).max()) / 4.0, 0.1))
        for key in keys:
            state.handle_key(key)
        renderer = PreviewRenderer(ctx, asset, state.current_sh(), cfg.shading)
        offscreen = OffscreenPreview(asset, ctx=ctx, renderer=renderer)  # screenshots: same renderer, no MSAA
        mouse = {"pos": None, "button": None}

        def on_key(win, key, scancode, action, mods):
            if action == glfw.PRESS:
                name = _key_name(glfw, key)
                msg = state.handle_key(name) if name else None
                if msg:
                    log(f"[dars view] {msg}")

        def on_button(win, button, action, mods):
            if action == glfw.PRESS:
                mouse["button"] = "left" if button == glfw.MOUSE_BUTTON_LEFT else "right"
                mouse["pos"] = glfw.get_cursor_pos(win)
            else:
                mouse["button"] = None

        def on_cursor(win, x, y):
            if mouse["button"] and mouse["pos"] is not None:
                state.handle_drag(x - mouse["pos"][0], y - mouse["pos"][1], mouse["button"])
                mouse["pos"] = (x, y)

        glfw.set_key_callback(window, on_key)
        glfw.set_mouse_button_callback(window, on_button)
        glfw.set_cursor_pos_callback(window, on_cursor)
        glfw.set_scroll_callback(window, lambda win, dx, dy: state.handle_scroll(dy))
        log("[dars view] h: help; 1-6 modes; tab orbit/walk; +/- exposure; l light; p screenshot; esc quit")
        frames, last = 0, time.perf_counter()
        sh_shown = None
        while not glfw.window_should_close(window) and not state.quit_requested:
            glfw.poll_events()
            now = time.perf_counter()
            held = {k for k in "wasdqe" if glfw.get_key(window, getattr(glfw, f"KEY_{k.upper()}")) == glfw.PRESS}
            state.update(now - last, held)
            last = now
            sh = state.current_sh()
            if sh_shown is None or not np.array_equal(sh, sh_shown):
                renderer.set_sh(sh)
                sh_shown = sh
            fb_w, fb_h = glfw.get_framebuffer_size(window)
            if fb_w > 0 and fb_h > 0:
                cam = state.camera(fb_w, fb_h)
                renderer.render(cam, state.cfg, ctx.detect_framebuffer())
                if state.screenshot_requested:
                    state.screenshot_requested = False
                    shot = offscreen.render(cam, state.cfg)
                    path = Path(screenshot_dir) / f"dars_view_{time.strftime('%Y%m%d_%H%M%S')}_{frames:05d}.png"
                    write_png(path, shot.to_float())
                    written.append(path)
                    log(f"[dars view] wrote {path}")
            glfw.swap_buffers(window)
            frames += 1
            if max_frames is not None and frames >= max_frames:
                break
        offscreen.release()
        renderer.release()
        glfw.destroy_window(window)
    finally:
        glfw.terminate()
    return written
