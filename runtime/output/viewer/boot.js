// The page's loader: everything is inside the page (nothing is fetched). It inflates the storm's
// data and the vendored three.js modules (zlib, base64 in <script type="application/octet-stream">
// elements), turns the modules into blob: URLs, points their imports at one another, and starts
// the viewer (app.js). A failure is shown on the page and logged as an error.
(function () {
  'use strict';
  function text(id) { return document.getElementById(id).textContent; }
  function fail(err) {
    const box = document.getElementById('hs-error');
    box.hidden = false;
    box.textContent = 'The viewer could not start: ' + (err && err.message ? err.message : String(err));
    console.error(err);
  }
  async function inflate(id) {
    const b64 = text(id).replace(/\s+/g, '');
    const bin = atob(b64);
    const bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('deflate'));
    return new Response(stream).arrayBuffer();
  }
  function moduleUrl(source) {
    return URL.createObjectURL(new Blob([source], { type: 'text/javascript' }));
  }
  function replaceAll(source, from, to, expected) {
    const parts = source.split(from);
    if (parts.length - 1 !== expected) {
      throw new Error('vendored module: expected ' + expected + ' import(s) of ' + from + ', found ' + (parts.length - 1));
    }
    return parts.join(to);
  }
  async function start() {
    if (typeof DecompressionStream === 'undefined') {
      throw new Error('this browser has no DecompressionStream (Chrome 80, Firefox 113, Safari 16.4 or newer)');
    }
    const dec = new TextDecoder();
    const meta = JSON.parse(text('hs-meta'));
    const [buffer, impacts, core, module, orbit, app] = await Promise.all(
      ['hs-data', 'hs-impacts', 'hs-three-core', 'hs-three-module', 'hs-three-orbit', 'hs-app'].map(inflate));
    const coreUrl = moduleUrl(dec.decode(core));
    const threeUrl = moduleUrl(replaceAll(dec.decode(module), "'./three.core.js'", JSON.stringify(coreUrl), 2));
    const orbitUrl = moduleUrl(replaceAll(dec.decode(orbit), "from 'three'", 'from ' + JSON.stringify(threeUrl), 1));
    let appSource = replaceAll(dec.decode(app), "from 'three'", 'from ' + JSON.stringify(threeUrl), 1);
    appSource = replaceAll(appSource, "from 'three/addons/controls/OrbitControls.js'",
      'from ' + JSON.stringify(orbitUrl), 1);
    const lines = dec.decode(impacts);
    meta.impacts.lines = meta.impacts.count ? lines.split('\n') : [];
    window.__hailstorm = { meta: meta, buffer: buffer };
    await import(moduleUrl(appSource));
  }
  window.addEventListener('DOMContentLoaded', function () { start().catch(fail); });
})();
