"""Numpy statements of algorithms whose one library implementation is a compiled kernel.

Test oracles only (the way pyamg keeps ``*_ref`` references for its compiled
core): the library never imports them.
"""
