"""Viewers and notebook widgets. They read SLAM state and call pipeline methods; the core never imports them.

- :mod:`.server`: a meshcat server on 127.0.0.1, stopped with its owner
- :mod:`.meshcat_view`: :class:`MapView`, the 3D map (points, keyframe frustums, path, current frame)
- :mod:`.frame_view`: OpenCV drawings (flow lines, keyframe matches) and the per-frame summary
- :mod:`.app`: :class:`SlamApp`, the ipywidgets app composing controls and views
"""
