"""Plain numpy statements of the storm's algorithms: oracles the tests hold the compiled kernels to
(never called by the library; the way pyamg keeps ``*_ref`` references for its compiled core)."""
