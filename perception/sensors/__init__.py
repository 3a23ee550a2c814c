"""Sensor models that shape simulated contact into the four recorded streams (see :mod:`perception.tactile`).

One job per module:

- :mod:`.resample`: rational-rate resampling with anti-aliasing and clock offsets.
- :mod:`.texture`: an object's random surface height field, from its material's roughness spectrum.
- :mod:`.contact_excitation`: texture and stick-slip modulation of the contact forces, at audio rate.
- :mod:`.taxels`: the uSkin-style 4 x 4 three-axis taxel array (N and F streams).
- :mod:`.imu`: the fingertip accelerometer (A stream).
- :mod:`.sound`: modal synthesis of the object's response and the microphone (S stream).
- :mod:`.environment`: ``clean`` and ``fire`` environment profiles and their noise sources.

All of it is pure numpy/scipy: nothing here imports a simulator.
"""
