// Default hailstorm seat: a solid bicycle saddle (metres, z up, nose at x = 0).
//
// About 270 mm long; a narrow nose (~40 mm) widening to a ~145 mm rear;
// a crowned top that dips slightly mid-length; 34-42 mm thick; flat underside.
// Built by lofting cross-sections (OpenCASCADE ThruSections), then imprinting
// the clamp patch (where the rails / seat post hold it) on the underside.
//
// Physical groups (the names the pipeline relies on):
//   Volume  "seat"  - the solid
//   Surface "top"   - every face hail can reach (all but the underside)
//   Surface "clamp" - the rail patch on the underside: zero displacement
//
// Mesh sizes are NOT set here: `hailstorm.precompute.geometry` sets them from
// --mesh-size (finest on "top"), so the same file serves every resolution.

SetFactory("OpenCASCADE");

// stations along the length: x, width, crown height, edge height (metres)
N = 11;
X[] = {0.000, 0.010, 0.035, 0.070, 0.110, 0.150, 0.185, 0.215, 0.243, 0.261, 0.270};
W[] = {0.020, 0.034, 0.041, 0.044, 0.056, 0.085, 0.118, 0.140, 0.146, 0.132, 0.096};
HC[] = {0.033, 0.036, 0.038, 0.036, 0.034, 0.034, 0.036, 0.039, 0.042, 0.041, 0.038};
HE[] = {0.024, 0.023, 0.022, 0.020, 0.019, 0.019, 0.020, 0.021, 0.023, 0.024, 0.024};

// fractions across the half-width where the crown spline passes
F[] = {1.0, 0.8, 0.45, 0.0, -0.45, -0.8, -1.0};

p = 1; c = 1;
For i In {0:N-1}
  x = X[i]; hw = W[i] / 2; hc = HC[i]; he = HE[i];
  Point(p) = {x, -hw, 0}; pbl = p; p++;
  Point(p) = {x,  hw, 0}; pbr = p; p++;
  tops[] = {};
  For j In {0:#F[]-1}
    y = F[j] * hw;
    Point(p) = {x, y, he + (hc - he) * (1 - F[j]^2)^0.55};
    tops[] += {p}; p++;
  EndFor
  Line(c) = {pbl, pbr}; cb = c; c++;
  Line(c) = {pbr, tops[0]}; cr = c; c++;
  Spline(c) = tops[]; ct = c; c++;
  Line(c) = {tops[#tops[]-1], pbl}; cl = c; c++;
  Wire(i + 1) = {cb, cr, ct, cl};
EndFor

ThruSections(1) = {1:N};

// the clamp patch: rails held between x = 120 and 205 mm, 44 mm wide
Rectangle(100) = {0.120, -0.022, 0, 0.085, 0.044};
BooleanFragments{ Volume{1}; Delete; }{ Surface{100}; Delete; }

eps = 1e-6;
bottom[] = Surface In BoundingBox{-1, -1, -eps, 1, 1, eps};
clamp[] = Surface In BoundingBox{0.120 - eps, -0.022 - eps, -eps, 0.205 + eps, 0.022 + eps, eps};
top[] = Abs(Boundary{ Volume{:}; });
top[] -= bottom[];

Physical Volume("seat") = {Volume{:}};
Physical Surface("top") = {top[]};
Physical Surface("clamp") = {clamp[]};
