"""Viewers and notebook widgets. They read SLAM state and call pipeline methods; the core never imports them.

- :mod:`.server`: a meshcat server on 127.0.0.1, stopped with its owner (:mod:`._meshcat_server` is its process)
- :mod:`.meshcat_view`: :class:`MapView`, the 3D map (points, keyframe frustums, path, current frame); one
  update reads a snapshot, diffs it against the scene and sends the difference, through
  - :mod:`.snapshot`: :class:`MapState` and reading points and poses from a pycolmap map
  - :mod:`.diff`: what changed between the scene and a new reading (pure numpy) and the point store
  - :mod:`.shown`: the map as the scene shows it (what the next reading is diffed against)
  - :mod:`.sender`: the one object sending meshcat commands, part by part
  - :mod:`.scene`: meshcat objects built from arrays (pure); :mod:`.settings`: what the view shows
- :mod:`.frame_view`: OpenCV drawings (flow lines, keyframe matches) and the per-frame summary
- :mod:`.app`: :class:`SlamApp`, the ipywidgets app's controller; :mod:`.app_widgets` its widgets and layout
"""
