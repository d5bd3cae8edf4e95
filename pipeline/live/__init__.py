"""The live loop: visual touch-ups measured on a robot, the loop as a library.

(Named for what it is, apart from :mod:`pipeline.measurement`, the equations.)

One loop serves every client: the simulator's recorder, ``vtcal measure`` on a
live cell through an adapter, and the tests. The loop sees the robot and the
camera only through the two small protocols of :mod:`pipeline.live.protocols`.
The simulator is a client above this package (:mod:`pipeline.sim.link`); the adapter
strings that pick a live or a simulated cell are :mod:`pipeline.sim.adapters`.
"""
