// A two-layer pad: a soft foam "pad" on a stiff "shell", clamped underneath.
// (metres, z up). Used by examples/layered_materials.py and docs "Command line":
//
//   hailstorm precompute --geometry examples/geometries/layered.geo \
//       --material pad=0.5e6,0.3 --material shell=2e9,0.4 --mesh-size 0.004 --coarsening 1 --out layered-gf
//
// Physical groups (the names hailstorm relies on):
//   Volume  "pad", "shell" - one material each (--material NAME=E,nu)
//   Surface "top"          - the hail-facing surface: gets columns of D and the fine mesh size
//   Surface "clamp"        - the shell's underside, fixed
// Mesh sizes are not set here: --mesh-size sets them (finest on "top"). Each layer needs
// about two elements across its thickness (hailstorm warns about a layer thinner than one):
// --mesh-size 0.004 --coarsening 1 (the same size throughout) resolves both.

SetFactory("OpenCASCADE");

L = 0.08;        // length [m]
W = 0.05;        // width [m]
T_SHELL = 0.008; // shell thickness [m]
T_PAD = 0.012;   // pad thickness [m]
e = 1e-6;

Box(1) = {0, 0, 0, L, W, T_SHELL};
Box(2) = {0, 0, T_SHELL, L, W, T_PAD};
BooleanFragments{ Volume{1}; Delete; }{ Volume{2}; Delete; }   // one conforming interface

shell() = Volume In BoundingBox{-e, -e, -e, L + e, W + e, T_SHELL + e};
pad() = Volume In BoundingBox{-e, -e, T_SHELL - e, L + e, W + e, T_SHELL + T_PAD + e};
bottom() = Surface In BoundingBox{-e, -e, -e, L + e, W + e, e};
upper() = Surface In BoundingBox{-e, -e, T_SHELL + T_PAD - e, L + e, W + e, T_SHELL + T_PAD + e};

Physical Volume("shell") = {shell()};
Physical Volume("pad") = {pad()};
Physical Surface("clamp") = {bottom()};
Physical Surface("top") = {upper()};
