"use strict";
// The registration page: two files -> POST v1/register/view -> pose, quality, warnings, timings and
// the clouds before/after in a PointViewer; the aligned source comes from POST v1/register/aligned.
(function () {
  const COLORS = {source: [255, 140, 0], target: [30, 144, 255]}; // = --source, --target in page.css
  const $ = (id) => document.getElementById(id);
  const params = new URLSearchParams(location.search);
  const viewer = new PointViewer($("canvas"), {renderer: params.get("renderer") || "webgl"});
  let last = null; // {result, files}
  let running = false;
  $("renderer").textContent = viewer.renderer;
  document.body.dataset.renderer = viewer.renderer;

  for (const name of ["source", "target"]) {
    const input = $(name), zone = $("drop-" + name);
    const show = () => { $(name + "-name").textContent = input.files.length ? input.files[0].name : "choose or drop a file"; };
    input.addEventListener("change", () => { show(); filesChanged(); });
    zone.addEventListener("dragover", (e) => { e.preventDefault(); zone.classList.add("over"); });
    zone.addEventListener("dragleave", () => zone.classList.remove("over"));
    zone.addEventListener("drop", (e) => {
      e.preventDefault();
      zone.classList.remove("over");
      if (e.dataTransfer.files.length) {
        const one = new DataTransfer();
        one.items.add(e.dataTransfer.files[0]);
        input.files = one.files;
        show();
        filesChanged();
      }
    });
  }

  let cancelRun = null;  // aborts the registration in flight, if any
  // A file chosen anew: the shown pose, view and download were another pair's.
  function filesChanged() {
    if (cancelRun) cancelRun();
    if (last) {
      clearResult();
      setStatus("Files changed: press Register for this pair.");
    }
  }

  $("api_key").addEventListener("input", () => {
    $("api_key").removeAttribute("aria-invalid");
    $("api_key").removeAttribute("aria-describedby");
  });

  function headers() {
    const key = $("api_key").value.trim();
    if (/[^\x20-\x7e]/.test(key)) {  // fetch() refuses header values outside Latin-1 with a TypeError
      $("api_key").setAttribute("aria-invalid", "true");
      $("api_key").setAttribute("aria-describedby", "status");
      $("api_key").focus();
      throw new Error("The API key holds a character that cannot be sent (only printable ASCII): check the \"API key\" field.");
    }
    return key ? {Authorization: "Bearer " + key} : {};
  }

  async function errorText(response) {
    let text;
    try {
      const body = await response.json();
      text = `${response.status}: ${body.error || JSON.stringify(body)}`;
    } catch (_) {
      text = `${response.status} ${response.statusText || "error"}`;
    }
    if (response.status === 401) {  // the server's words name a header: say where a page user gives the key
      text += "\nEnter the server's API key in the \"API key\" field (Options) and try again.";
      $("api_key").setAttribute("aria-invalid", "true");  // the field in error, described by the message
      $("api_key").setAttribute("aria-describedby", "status");
      $("api_key").focus();
    }
    return text;
  }

  // POST a form; the response, or an Error whose message says what went wrong in the user's words.
  async function post(url, form, signal) {
    let response;
    const sent = headers();  // an Error naming the key field where the key cannot be sent
    try {
      response = await fetch(url, {method: "POST", body: form, headers: sent, signal});
    } catch (err) {
      if (err.name === "AbortError") throw err;
      // fetch() rejects (a TypeError: "Failed to fetch") only when no answer arrives
      throw new Error(`No answer from the server (${err.message}): is it running and reachable? Try again.`);
    }
    if (!response.ok) throw new Error(await errorText(response));
    return response;
  }

  const failureText = (err) => (err && err.name === "AbortError" ? "Cancelled." : String((err && err.message) || err));

  function setStatus(text, isError = false) {
    $("status").textContent = text;
    $("status").className = isError ? "error" : "";
  }

  // base64 of float32 little-endian [n, 3] rows (every browser platform in use is little-endian).
  function decodePoints(b64) {
    const text = atob(b64);
    const bytes = new Uint8Array(text.length);
    for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
    return new Float32Array(bytes.buffer);
  }

  $("form").addEventListener("submit", async (e) => {
    e.preventDefault();
    if (running) return;  // Enter again on Register or in a field while this pair runs
    const chosen = {source: $("source").files[0], target: $("target").files[0]};
    if (!chosen.source || !chosen.target) return setStatus("Choose a source and a target file.", true);
    let files;
    running = true;  // from here: a second Enter while the source is read sends nothing
    document.body.dataset.state = "running";
    try {  // the bytes registered, kept for the download: the file on disk may be rewritten meanwhile
      files = {source: new File([await chosen.source.arrayBuffer()], chosen.source.name), target: chosen.target};
    } catch (err) {
      running = false;
      document.body.dataset.state = "error";
      return setStatus(`Could not read ${chosen.source.name}: ${err.message}`, true);
    }
    const form = new FormData();
    form.append("source", files.source, files.source.name);
    form.append("target", files.target, files.target.name);
    for (const name of ["refine", "rotation_search"]) if ($(name).value) form.append(name, $(name).value);
    form.append("drop_isolated", $("drop_isolated").checked ? "true" : "false");
    form.append("return_correspondences", "false");
    document.body.dataset.state = "running";
    running = true;
    clearResult();  // until this pair's answer: never the last pair's pose, view or download under this one's status
    // aria-disabled, not disabled: a disabled button loses the keyboard focus (to the page's start)
    $("register").setAttribute("aria-disabled", "true");
    const started = performance.now();
    const elapsed = () => `${Math.round((performance.now() - started) / 1000)} s`;
    setStatus("Uploading and registering…");  // once: a live region that changes every second is read every second
    const ticker = setInterval(() => { $("elapsed").textContent = `${elapsed()} so far`; }, 1000);
    const abort = new AbortController();
    const cancel = () => abort.abort();
    cancelRun = cancel;
    $("cancel").hidden = false;
    $("cancel").addEventListener("click", cancel);
    try {
      const response = await post("v1/register/view", form, abort.signal);
      const body = await response.json();
      last = {result: body.result, files};
      viewer.setClouds([
        {name: "target", points: decodePoints(body.display.target.xyz), origin: body.display.target.origin,
          color: COLORS.target},
        {name: "source", points: decodePoints(body.display.source.xyz), origin: body.display.source.origin,
          color: COLORS.source},
      ]);
      showView(true);
      showResult(body.result);
      const d = body.display;
      $("shown").textContent = `Shown: source ${d.source.shown} of ${d.source.points} points, target ` +
        `${d.target.shown} of ${d.target.points} (at most ${d.cap} per cloud).`;
      const q = body.result.quality, count = body.result.warnings.length;  // the live region says what came
      setStatus(`Done in ${Math.round(performance.now() - started)} ms: ${q.reliable ? "reliable" : "not reliable"}, ` +
        `${count ? count + (count === 1 ? " warning" : " warnings") : "no warnings"}.`);
      document.body.dataset.state = "done";
    } catch (err) {
      clearResult();
      const cancelled = err && err.name === "AbortError";
      setStatus(failureText(err), !cancelled);
      document.body.dataset.state = cancelled ? "cancelled" : "error";
    } finally {
      clearInterval(ticker);
      $("elapsed").textContent = "";
      $("cancel").removeEventListener("click", cancel);
      if (cancelRun === cancel) cancelRun = null;
      // hiding the focused Cancel would drop the keyboard focus to the page's start: back to Register
      if (document.activeElement === $("cancel")) $("register").focus();
      $("cancel").hidden = true;
      $("register").removeAttribute("aria-disabled");
      running = false;
    }
  });

  function clearResult() {
    last = null;
    $("result").hidden = true;
    $("shown").textContent = "";
    viewer.setClouds([]);
  }

  function showView(after) {
    viewer.setPose("source", after && last ? last.result.transform : null);
    $("show-after").classList.toggle("active", after);
    $("show-before").classList.toggle("active", !after);
    $("show-after").setAttribute("aria-pressed", String(after));
    $("show-before").setAttribute("aria-pressed", String(!after));
  }

  $("show-before").addEventListener("click", () => showView(false));
  $("show-after").addEventListener("click", () => showView(true));
  $("reset-view").addEventListener("click", () => viewer.resetView());

  const fmt = (v, digits = 6) => (typeof v === "number" ? Number(v.toPrecision(digits)).toString() : String(v));

  function fillTable(table, rows) {
    table.replaceChildren(...rows.map(([key, value]) => {
      const tr = document.createElement("tr");
      for (const text of [key, value]) {
        const td = document.createElement("td");
        td.textContent = text;
        tr.append(td);
      }
      return tr;
    }));
  }

  function showResult(result) {
    $("result").hidden = false;
    // every digit: 5 significant ones moved map (UTM) coordinates by tens of metres; the block scrolls sideways
    const cells = result.transform.map((row) => row.map((v) => String(v)));
    const width = Math.max(...cells.flat().map((c) => c.length));
    $("transform").textContent = cells.map((row) => row.map((c) => c.padStart(width)).join(" ")).join("\n");
    $("euler").textContent = result.euler_zyx_deg.map((v) => fmt(v, 9)).join(", ");
    $("ypr").textContent = result.yaw_pitch_roll_deg.map((v) => fmt(v, 9)).join(", ");
    const q = result.quality;
    $("reliable").textContent = q.reliable ? "(reliable)" : "(not reliable)";
    $("reliable").className = q.reliable ? "yes" : "no";
    fillTable($("quality"), [
      ["inlier ratio", fmt(q.inlier_ratio, 4)],
      ["residual RMS", fmt(q.residual_rms, 4)],
      ["stability", q.stability == null ? "n/a" : fmt(q.stability, 4)],
      ["reliable", String(q.reliable)],
    ]);
    const warnings = result.warnings.length ? result.warnings : ["none"];
    $("warnings").replaceChildren(...warnings.map((w) => Object.assign(document.createElement("li"), {textContent: w})));
    fillTable($("timings"), Object.entries(result.timing_ms).map(([k, v]) => [k, fmt(v, 4)]));
    $("model").textContent = `${result.model.name} ${result.model.version}`;
  }

  let downloading = null;  // the pair whose aligned source is being prepared
  $("download").addEventListener("click", async () => {
    if (!last || downloading === last) return;  // a second press for this pair while it is prepared: one file, not two
    const pair = last;  // a registration started meanwhile owns the status line from then on
    downloading = pair;
    const form = new FormData();
    form.append("source", last.files.source, last.files.source.name);
    form.append("transform", JSON.stringify(last.result.transform));
    setStatus("Preparing the aligned source…");
    try {
      const response = await post("v1/register/aligned", form);
      const blob = await response.blob();
      const disposition = response.headers.get("Content-Disposition") || "";
      const utf8 = /filename\*=UTF-8''([^;]+)/i.exec(disposition);  // RFC 6266: the name as sent, where not ASCII
      const plain = /filename="([^"]+)"/.exec(disposition);
      const link = Object.assign(document.createElement("a"), {
        href: URL.createObjectURL(blob),
        download: utf8 ? decodeURIComponent(utf8[1]) : plain ? plain[1] : "aligned_source.ply",
      });
      document.body.append(link);
      link.click();
      link.remove();
      setTimeout(() => URL.revokeObjectURL(link.href), 10000);
      if (last === pair) setStatus("Aligned source downloaded.");
    } catch (err) {
      if (last === pair) setStatus(failureText(err), true);
    } finally {
      if (downloading === pair) downloading = null;
    }
  });
})();
