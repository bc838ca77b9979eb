"""The only GL code in crowdbake: offscreen rendering with pyrender (OSMesa or EGL)."""
