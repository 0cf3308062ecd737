"""Franka Research 3 emulator: franka-sim (the libfranka-protocol simulator, MuJoCo physics) in its own
environment, serving a station world's true arm and cell; the real ``pylibfranka`` client talks to it unchanged.
``station mock franka --world FILE`` (``cli.py``) writes the scene (``scene.py``) and runs ``simhost.py`` in the
franka-sim environment (``simenv.py``); ``launch.FrankaEmulator`` does the same for tests and scripts."""
