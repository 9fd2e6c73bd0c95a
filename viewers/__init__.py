"""Viewers of a baked asset (SPEC stage 15): the moderngl desktop preview and the WebXR page.

* :mod:`viewers.shading_glsl` — the GLSL generated from :mod:`toolkit.shading` (one shading, held together by a test).
* :mod:`viewers.preview` — headless / in-window moderngl rendering of a GLB (lit, albedo, roughness, metallic,
  normals, semantics); :func:`viewers.preview.render_preview` renders one PNG-ready image.
* :mod:`viewers.camera` — the glTF axis conversion of :class:`toolkit.pinhole.PinholeCamera`, framing, orbit and walk
  controllers.
* :mod:`viewers.gl` — the headless OpenGL (EGL) context.
* :mod:`viewers.lighting` — the SH light of a GLB, a JSON file or an HDR probe (relighting).
* :mod:`viewers.window` — the interactive glfw window (``dars view ASSET``).
* :mod:`viewers.web` — the static three.js / WebXR page (``dars export-web``).

Submodules import moderngl (and glfw for the window) lazily where they can; nothing here is imported by ``toolkit``
except inside the ``dars view`` / ``dars export-web`` command handlers.
"""
