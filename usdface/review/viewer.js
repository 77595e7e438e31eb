// usdface review page glue: blends the embedded sparse shape deltas and updates plotly's Mesh3d traces.
// Data: window.USDFACE_DATA (see usdface/review/page.py). URL parameters (for links and tests):
//   shape=jawOpen,eyeBlinkLeft & w=1,0.5   set sliders      preset=smile       a named pose
//   variant=generic|personalized           one variant, full width (default: both side by side)
//   heat=rms|pose   heat map on the personalized face      landmarks=0|1
//   seq=<index> & frame=<n>                show a frame of a sequence (0: test expressions, 1: take)
function usdfaceStart(plotId) {
  "use strict";
  var D = window.USDFACE_DATA, gd = document.getElementById(plotId);
  var status = document.getElementById("usdface-status"), panel = document.getElementById("usdface-panel");
  var K = D.names.length, weights = new Float64Array(K), params = new URLSearchParams(location.search);
  var state = {heat: "off", variant: "split", landmarks: true, playing: false, seq: 0, frame: 0};

  function bytes(b64) {
    var s = atob(b64), out = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
    return out.buffer;
  }
  function shapes(list, n) {
    return list.map(function (e) {
      return {idx: n < 65536 ? new Uint16Array(bytes(e.idx)) : new Uint32Array(bytes(e.idx)),
              q: new Int16Array(bytes(e.q)), s: e.s};
    });
  }
  // traces: per scene (generic, personalized) one Mesh3d per mesh, then one Scatter3d per landmark set
  var M = D.meshes.length, nLm = 0;
  D.meshes.forEach(function (m, i) {
    m.base = new Float32Array(bytes(m.neutral));
    if (m.generic) { m.g = shapes(m.generic, m.n); m.c = shapes(m.change, m.n); }
    if (m.heat) m.heatMm = new Float32Array(bytes(m.heat));
    if (m.landmarks) { m.lmTrace = [M + nLm, 2 * M + (function () { return 0; })()]; nLm++; }
  });
  var perScene = M + nLm, lm = 0;
  D.meshes.forEach(function (m, i) {
    m.trace = [i, perScene + i];
    if (m.landmarks) { m.lmTrace = [M + lm, perScene + M + lm]; lm++; }
  });
  D.sequences.forEach(function (s) { s.W = new Uint8Array(bytes(s.w)); });

  function add(out, list, a, w) {  // out += w * sparse delta a of list
    var sh = list[a], f = w * sh.s, idx = sh.idx, q = sh.q;
    for (var j = 0; j < idx.length; j++) {
      var o = 3 * idx[j], r = 3 * j;
      out[o] += f * q[r]; out[o + 1] += f * q[r + 1]; out[o + 2] += f * q[r + 2];
    }
  }
  function pose(m, variant) {  // Float32Array [n*3] of the deformed mesh; personalized = generic + change
    var out = new Float32Array(m.base);
    if (!m.g) return out;
    for (var a = 0; a < m.shapes.length; a++) {
      var w = weights[m.shapes[a]];
      if (!w) continue;
      add(out, m.g, a, w);
      if (variant !== "generic") add(out, m.c, a, w);
    }
    return out;
  }
  function split(p) {
    var n = p.length / 3, x = new Float32Array(n), y = new Float32Array(n), z = new Float32Array(n);
    for (var i = 0; i < n; i++) { x[i] = p[3 * i]; y[i] = p[3 * i + 1]; z[i] = p[3 * i + 2]; }
    return [x, y, z];
  }
  function pick(p, idx) {
    var x = [], y = [], z = [];
    idx.forEach(function (i) { x.push(p[3 * i]); y.push(p[3 * i + 1]); z.push(p[3 * i + 2]); });
    return [x, y, z];
  }

  var busy = false, pending = false;
  function update() {
    if (busy) { pending = true; return Promise.resolve(); }
    busy = true;
    var X = [], Y = [], Z = [], I = [], C = [], S = [], CMAX = [];
    var left = state.variant === "split" ? "generic" : state.variant;
    D.meshes.forEach(function (m) {
      var pl = pose(m, left), pr = pose(m, "personalized"), a = split(pl), b = split(pr);
      X.push(a[0], b[0]); Y.push(a[1], b[1]); Z.push(a[2], b[2]); I.push(m.trace[0], m.trace[1]);
      var heat = null, top = 1;
      if (state.heat === "rms" && m.heatMm) {
        heat = m.heatMm;
      } else if (state.heat === "pose" && m.generic) {
        var pg = pose(m, "generic");
        heat = new Float32Array(m.n);
        for (var i = 0; i < m.n; i++) {
          var dx = pr[3 * i] - pg[3 * i], dy = pr[3 * i + 1] - pg[3 * i + 1], dz = pr[3 * i + 2] - pg[3 * i + 2];
          heat[i] = 1000 * Math.sqrt(dx * dx + dy * dy + dz * dz);
        }
      }
      if (heat) { for (var h = 0; h < heat.length; h++) if (heat[h] > top) top = heat[h]; }
      var lh = left === "personalized" ? heat : null;  // heat is on whichever scene shows personalized
      C.push(lh, heat); S.push(!!lh && m.role === "skin", !!heat && m.role === "skin"); CMAX.push(top, top);
      if (m.landmarks) {
        var la = pick(pl, m.landmarks), lb = pick(pr, m.landmarks);
        X.push(la[0], lb[0]); Y.push(la[1], lb[1]); Z.push(la[2], lb[2]); I.push(m.lmTrace[0], m.lmTrace[1]);
        C.push(undefined, undefined); S.push(undefined, undefined); CMAX.push(undefined, undefined);
      }
    });
    var upd = {x: X, y: Y, z: Z};
    if (state.heatChanged) {
      upd.intensity = C; upd.showscale = S; upd.cmin = C.map(function (c) { return c === undefined ? undefined : 0; });
      upd.cmax = CMAX; upd.colorscale = C.map(function () { return "Hot"; });
      state.heatChanged = false;
    } else if (state.heat === "pose") {
      upd.intensity = C; upd.cmax = CMAX;
    }
    return Plotly.restyle(gd, upd, I).then(function () {
      busy = false;
      if (pending) { pending = false; return update(); }
    });
  }

  // ---- panel ----
  function el(tag, attrs, parent) {
    var e = document.createElement(tag);
    Object.keys(attrs || {}).forEach(function (k) { if (k === "text") e.textContent = attrs[k]; else e.setAttribute(k, attrs[k]); });
    if (parent) parent.appendChild(e);
    return e;
  }
  var sliders = [];
  function setWeights(w) {
    for (var k = 0; k < K; k++) { weights[k] = w[k] || 0; sliders[k].value = weights[k]; }
  }
  el("h3", {text: "view"}, panel);
  var vsel = el("select", {id: "usdface-variant"}, panel);
  [["split", "generic | personalized"], ["generic", "generic only"], ["personalized", "personalized only"]].forEach(function (o) {
    el("option", {value: o[0], text: o[1]}, vsel);
  });
  var hsel = el("select", {id: "usdface-heat"}, panel);
  [["off", "no heat map"], ["rms", "heat: change, RMS over shapes (mm)"], ["pose", "heat: change at this pose (mm)"]].forEach(function (o) {
    el("option", {value: o[0], text: o[1]}, hsel);
  });
  var lmBox = null;
  if (nLm) {
    var lab = el("label", {}, panel); lmBox = el("input", {type: "checkbox", id: "usdface-landmarks"}, lab);
    lmBox.checked = true; lab.appendChild(document.createTextNode(" landmarks"));
  }
  el("h3", {text: "presets"}, panel);
  var pdiv = el("div", {}, panel);
  el("button", {text: "neutral", "data-preset": ""}, pdiv).onclick = function () { setWeights([]); update(); };
  Object.keys(D.presets).forEach(function (p) {
    el("button", {text: p, "data-preset": p}, pdiv).onclick = function () { applyPreset(p); update(); };
  });
  function applyPreset(p) {
    var w = []; Object.keys(D.presets[p]).forEach(function (n) { w[D.names.indexOf(n)] = D.presets[p][n]; });
    setWeights(w);
  }
  var seqSlider = null, seqLabel = null, seqSel = null, playBtn = null;
  if (D.sequences.length) {
    el("h3", {text: "playback"}, panel);
    seqSel = el("select", {id: "usdface-seq"}, panel);
    D.sequences.forEach(function (s, i) { el("option", {value: i, text: s.title + " (" + s.frames + " frames)"}, seqSel); });
    playBtn = el("button", {text: "play", id: "usdface-play"}, panel);
    seqSlider = el("input", {type: "range", min: 0, max: D.sequences[0].frames - 1, step: 1, value: 0, style: "width:100%"}, panel);
    seqLabel = el("div", {text: "", style: "font-size:11px"}, panel);
  }
  function showFrame(si, f) {
    var s = D.sequences[si], w = [];
    f = Math.max(0, Math.min(s.frames - 1, f | 0));
    for (var k = 0; k < K; k++) w[k] = s.W[f * K + k] / 255;
    setWeights(w);
    state.seq = si; state.frame = f;
    if (seqSlider) { seqSlider.value = f; seqLabel.textContent = s.times[f].toFixed(2) + " s  " + (s.labels[f] || ""); }
    return update();
  }
  el("h3", {text: "shapes"}, panel);
  D.names.forEach(function (n, k) {
    var lab = el("label", {"class": "sl", title: n}, panel);
    el("span", {text: n}, lab);
    var s = el("input", {type: "range", min: 0, max: 1, step: 0.01, value: 0, "data-shape": n}, lab);
    s.oninput = function () { weights[k] = parseFloat(s.value); update(); };
    sliders.push(s);
  });

  function setVariant(v) {
    state.variant = v; state.heatChanged = true;
    var single = v !== "split", lay = {};
    lay["scene.domain.x"] = single ? [0, 1] : [0, 0.5];
    lay["scene2.domain.x"] = single ? [0.999, 1] : [0.5, 1];
    lay["annotations[0].text"] = single ? v : "generic";
    lay["annotations[0].x"] = single ? 0.5 : 0.25;
    lay["annotations[1].visible"] = !single;
    var right = []; for (var t = perScene; t < 2 * perScene; t++) right.push(t);
    return Plotly.relayout(gd, lay).then(function () { return Plotly.restyle(gd, {visible: !single}, right); });
  }
  function setLandmarks(on) {
    state.landmarks = on;
    var idx = []; D.meshes.forEach(function (m) { if (m.landmarks) idx.push(m.lmTrace[0], m.lmTrace[1]); });
    if (!idx.length) return Promise.resolve();
    var vis = idx.map(function (t) { return on && (t < perScene || state.variant === "split"); });
    return Plotly.restyle(gd, {visible: vis}, idx);
  }
  vsel.onchange = function () { setVariant(vsel.value).then(function () { return setLandmarks(state.landmarks); }).then(update); };
  hsel.onchange = function () { state.heat = hsel.value; state.heatChanged = true; update(); };
  if (lmBox) lmBox.onchange = function () { setLandmarks(lmBox.checked); };

  // shared camera: orbiting one scene moves the other
  var syncing = false;
  gd.on("plotly_relayout", function (ev) {
    if (syncing) return;
    var cam = ev["scene.camera"] ? ["scene2.camera", ev["scene.camera"]] : ev["scene2.camera"] ? ["scene.camera", ev["scene2.camera"]] : null;
    if (!cam) return;
    syncing = true;
    var lay = {}; lay[cam[0]] = cam[1];
    Plotly.relayout(gd, lay).then(function () { syncing = false; }, function () { syncing = false; });
  });

  if (seqSlider) {
    seqSel.onchange = function () {
      var s = D.sequences[+seqSel.value]; seqSlider.max = s.frames - 1; showFrame(+seqSel.value, 0);
    };
    seqSlider.oninput = function () { showFrame(+seqSel.value, +seqSlider.value); };
    var t0 = 0, f0 = 0;
    function tick(now) {
      if (!state.playing) return;
      var s = D.sequences[state.seq], t = s.times[f0] + (now - t0) / 1000, f = f0;
      while (f < s.frames - 1 && s.times[f + 1] <= t) f++;
      if (f >= s.frames - 1) { state.playing = false; playBtn.textContent = "play"; }
      (f !== state.frame ? showFrame(state.seq, f) : Promise.resolve()).then(function () { requestAnimationFrame(tick); });
    }
    playBtn.onclick = function () {
      state.playing = !state.playing; playBtn.textContent = state.playing ? "pause" : "play";
      if (state.playing) {
        state.seq = +seqSel.value;
        if (state.frame >= D.sequences[state.seq].frames - 1) state.frame = 0;
        f0 = state.frame; t0 = performance.now(); requestAnimationFrame(tick);
      }
    };
  }

  // ---- URL parameters, then first draw ----
  var chain = Plotly.Plots.resize(gd);  // fill the page's plot area (the figure was laid out before it)
  var v = params.get("variant");
  if (v === "generic" || v === "personalized") { vsel.value = v; chain = chain.then(function () { return setVariant(v); }); }
  var h = params.get("heat");
  if (h === "rms" || h === "pose") { hsel.value = h; state.heat = h; state.heatChanged = true; }
  if (params.get("landmarks") === "0" && lmBox) { lmBox.checked = false; chain = chain.then(function () { return setLandmarks(false); }); }
  if (params.get("preset") && D.presets[params.get("preset")]) applyPreset(params.get("preset"));
  if (params.get("shape")) {
    var ns = params.get("shape").split(","), ws = (params.get("w") || "1").split(",");
    ns.forEach(function (n, i) {
      var k = D.names.indexOf(n);
      if (k < 0) throw new Error("no shape " + n + " in this avatar");
      weights[k] = parseFloat(ws[Math.min(i, ws.length - 1)]); sliders[k].value = weights[k];
    });
  }
  var seqParam = params.get("seq");
  chain = chain.then(function () {
    if (seqParam !== null && D.sequences[+seqParam]) { seqSel.value = seqParam; seqSlider.max = D.sequences[+seqParam].frames - 1; return showFrame(+seqParam, +(params.get("frame") || 0)); }
    return update();
  });
  chain.then(function () {
    if (!status.textContent.startsWith("error")) status.textContent = "ok";
    console.log("usdface-status: " + status.textContent);  // for headless tests reading the console
    status.setAttribute("data-size", gd._fullLayout.width + "x" + gd._fullLayout.height);
  }, function (err) {
    status.textContent = "error: " + (err && err.message ? err.message : err); status.style.color = "#f66";
    console.log("usdface-status: " + status.textContent);
  });
}
