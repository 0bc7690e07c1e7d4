"""Driving bodies of your own with trained controllers: ``freeform-control`` (:mod:`freeform.control.cli`).

``evaluate`` plays a controller on bodies against their own gaits and the hand-set wave, ``watch`` renders one
body's gait under it, ``fit`` gives each body the best of the zoo's controllers by trial and adapts it by PPO.
"""
