// A user geometry: a rubber block with a rounded top edge, clamped on its underside
// (metres, z up). Used by examples/user_geometry.py and docs "Command line":
//
//   hailstorm precompute --geometry examples/geometries/block.geo --young 5e5 --poisson 0.4 \
//       --mesh-size 0.008 --out block-gf
//
// Physical groups (the names hailstorm relies on):
//   Surface "top"   - every face hail can reach (all but the underside)
//   Surface "clamp" - the underside, fixed
//   Volume  "block" - the solid (one material: --young/--poisson, or --material block=E,nu)
// Mesh sizes are not set here: --mesh-size sets them (finest on "top").

SetFactory("OpenCASCADE");

L = 0.06;   // length [m]
W = 0.04;   // width [m]
H = 0.02;   // height [m]
R = 0.006;  // radius of the rounded top edges [m]
e = 1e-6;

Box(1) = {0, 0, 0, L, W, H};
top_edges() = Curve In BoundingBox{-e, -e, H - e, L + e, W + e, H + e};
Fillet{1}{top_edges()}{R}

all() = Surface{:};
bottom() = Surface In BoundingBox{-e, -e, -e, L + e, W + e, e};
Physical Surface("clamp") = {bottom()};
Physical Surface("top") = {all()};
Physical Surface("top") -= {bottom()};
Physical Volume("block") = {Volume{:}};
