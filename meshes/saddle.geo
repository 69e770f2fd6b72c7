// Default hailstorm seat: a padded bicycle saddle (metres, z up, nose at x = 0).
//
// About 270 mm long; a narrow nose (~40 mm) widening to a ~145 mm rear. A real
// saddle is a stiff shell (nylon or carbon composite, GPa) under 12-15 mm of foam,
// held by rails under the shell. Here the shell is an arched plate whose top
// rises from z = 3 mm at the edges to 15-24 mm on the centre line (the hollow a
// saddle has underneath), and the pad follows it: 12 mm thick at the edges,
// 15 mm on the crown.
//
// Only the pad is meshed: the shell is its rigid base (the pad's underside is
// clamped). That is a measured choice for a carbon-composite shell: modelled as
// an elastic 3 mm plate (E = 50 GPa) held only at the rail sockets, the shell
// changes a stone's contact stiffness by less than 0.6 % (< 2 %: rigid base).
// A 3 mm nylon shell (3 GPa) would change it by 6-8 % mid-span: model that one
// as a second volume (docs "Choosing settings", "The default seat";
// `python -m studies.seat_study --shell --order 2 [--shell-young 3e9]`).
//
// Physical groups (the names the pipeline relies on):
//   Volume  "pad"   - the foam
//   Surface "top"   - every face hail can reach (all but the underside)
//   Surface "clamp" - the pad's underside, on the rigid shell
//
// Mesh sizes are NOT set here: `hailstorm.precompute.geometry` sets them from
// --mesh-size (finest on "top"), so the same file serves every resolution.

SetFactory("OpenCASCADE");

// stations along the length: x, width, shell-top rise on the centre line (metres)
N = 11;
X[] = {0.000, 0.010, 0.035, 0.070, 0.110, 0.150, 0.185, 0.215, 0.243, 0.261, 0.270};
W[] = {0.020, 0.034, 0.041, 0.044, 0.056, 0.085, 0.118, 0.140, 0.146, 0.132, 0.096};
RISE[] = {0.012, 0.015, 0.017, 0.015, 0.013, 0.013, 0.015, 0.018, 0.021, 0.020, 0.017};
TS = 0.003;      // shell thickness: the shell's top is its underside raised by TS
PAD_E = 0.012;   // pad thickness at the edges
PAD_C = 0.015;   // pad thickness on the crown

// fractions across the half-width where the splines pass (right to left)
F[] = {1.0, 0.8, 0.45, 0.0, -0.45, -0.8, -1.0};

p = 1; c = 1;
For i In {0:N-1}
  x = X[i]; hw = W[i] / 2; r = RISE[i];
  upper[] = {}; crown[] = {};
  For j In {0:#F[]-1}
    y = F[j] * hw; s = (1 - F[j]^2)^0.55;
    Point(p) = {x, y, r * s + TS}; upper[] += {p}; p++;
    Point(p) = {x, y, r * s + TS + PAD_E + (PAD_C - PAD_E) * s}; crown[] += {p}; p++;
  EndFor
  n = #F[] - 1;
  // pad section: shell top (right to left), left side up, crown (left to right), right side down
  Spline(c) = upper[]; cu = c; c++;
  Line(c) = {upper[n], crown[n]}; cl = c; c++;
  Spline(c) = {crown[{n:0:-1}]}; cc = c; c++;
  Line(c) = {crown[0], upper[0]}; cr = c; c++;
  Wire(i + 1) = {cu, cl, cc, cr};
EndFor

ThruSections(1) = {1:N};

// the pad's underside is the lofted shell-top spline: the face spanning the full length and width low down
faces[] = Abs(Boundary{ Volume{1}; });
bottom[] = {};
For k In {0:#faces[]-1}
  bb[] = BoundingBox Surface{faces[k]};
  If (bb[3] - bb[0] > 0.2 && bb[2] < TS + 1e-4 && bb[4] - bb[1] > 0.14)
    bottom[] += {faces[k]};
  EndIf
EndFor
top[] = faces[];
top[] -= bottom[];

Physical Volume("pad") = {1};
Physical Surface("top") = {top[]};
Physical Surface("clamp") = {bottom[]};
