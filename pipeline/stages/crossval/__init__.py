"""Which error model the run ships: held-out error of each, and the choice by it.

``stage`` (the crossval stage: k-fold and leave-one-target-out), ``refit`` (the refits
on subsets of one table), ``predict`` (held-out predictions), ``choose`` (the choose
stage: the shipped model and its summary).
"""
