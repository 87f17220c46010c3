import os

# Before anything imports OpenGL or warp: headless rendering, and keep warp's kernel cache out of the way.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("PYGLET_HEADLESS", "true")
