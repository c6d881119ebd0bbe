"""The relocalization methods of the thesis and what verifies them: place finders
(``place``), pose finders and the PnP solve (``pose``), random ferns (``ferns``), and the
relocalizers that combine them behind ``add_keyframe``, ``remove_keyframe``, ``train`` and
``relocalize`` (``relocalizers``, with the method-string ``factory``). Imports the core."""
