// Shared helpers of the annotation pages. Coordinates sent to the API are the label format's:
// boxes (ymin, xmin, ymax, xmax) and points (x, y) normalised to [0, 1] by the image size.
export const $ = (sel, root = document) => root.querySelector(sel);
export const el = (tag, attrs = {}, ...kids) => {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v; else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (v !== null && v !== undefined && v !== false) e.setAttribute(k, v === true ? "" : v);
  }
  for (const k of kids.flat()) if (k !== null && k !== undefined) e.append(k.nodeType ? k : document.createTextNode(k));
  return e;
};
export const media = (path) => "/" + path;   // warehouse-relative media paths start with "media/"
export const params = () => Object.fromEntries(new URLSearchParams(location.search));

// This tab's client id (kept in sessionStorage: a reload keeps it, another tab has its own): items a
// page opens are held for it (cadestate/webapp/claims.py), and the queue gives other tabs and
// browsers other items (one person working in two tabs is given two items).
const CLIENT_KEY = "cadestate-client";
const newClientId = () => Array.from(crypto.getRandomValues(new Uint8Array(12)), (b) => b.toString(16).padStart(2, "0")).join("");
let storedId = null;
const clientId = (() => {
  try {
    storedId = sessionStorage.getItem(CLIENT_KEY);
    const id = storedId || newClientId();
    if (!storedId) sessionStorage.setItem(CLIENT_KEY, id);
    return id;
  } catch (e) {  // storage refused (a private window's settings): this page's own id
    return newClientId();
  }
})();
const CLIENT_HEADER = {"X-Cadestate-Client": clientId};

// A tab the browser duplicates copies sessionStorage, this id with it: the two tabs were one client,
// given one item with no word, and closing either gave back the other's claim. Each page says its id
// on a BroadcastChannel when it loads; of two live pages with one id, the younger takes a new one.
// A page whose id came from storage waits a moment for the answer before its first request.
let onNewClientId = () => {};
const clientChecked = new Promise((checked) => {
  if (typeof BroadcastChannel === "undefined") { checked(); return; }
  if (!storedId) checked();  // a new id: no page has it (but this one answers a copy of itself)
  const born = performance.timeOrigin, channel = new BroadcastChannel("cadestate-client");
  channel.onmessage = ({data}) => {
    if (!data || data.id !== CLIENT_HEADER["X-Cadestate-Client"] || data.born === born) return;
    if (data.born > born) { channel.postMessage({id: data.id, born}); return; }  // the other page is the copy: tell it
    const id = newClientId();  // this page is the copy
    try { sessionStorage.setItem(CLIENT_KEY, id); } catch (e) { /* this page's own id, as above */ }
    CLIENT_HEADER["X-Cadestate-Client"] = id;
    checked();
    onNewClientId();
  };
  channel.postMessage({id: clientId, born});
  setTimeout(checked, 150);  // no other page of this id answered
});

export async function api(path, body) {
  const r = await fetch(path, body === undefined ? {headers: CLIENT_HEADER}
    : {method: "POST", headers: {"Content-Type": "application/json", ...CLIENT_HEADER}, body: JSON.stringify(body)});
  const data = await r.json().catch(() => null);
  if (!r.ok) throw new Error((data && (typeof data.detail === "string" ? data.detail : JSON.stringify(data.detail))) || r.statusText);
  return data;
}

// Messages at the bottom right: the live region is there from the page's start (a region made with its
// first message is not announced); an error is an alert. A warning stays until closed (✕).
const statusBox = () => $("#status") || document.body.appendChild(el("div", {id: "status", role: "status", "aria-live": "polite"}));
statusBox();  // a module runs once the page is parsed
export function toast(text, kind = "") {
  const t = el("div", {class: "toast " + kind, ...(kind === "error" ? {role: "alert"} : {})}, text);
  if (kind === "warn") t.append(el("button", {class: "close", title: "close", "aria-label": "close this warning", onclick: () => t.remove()}, "✕"));
  statusBox().append(t);
  if (kind !== "warn" && !(text instanceof Node)) setTimeout(() => t.remove(), kind === "error" ? 12000 : 5000);
  return t;
}

// Seconds spent on the item shown: counts only while the page is visible.
export function timer() {
  let total = 0, since = performance.now();
  document.addEventListener("visibilitychange", () => {
    if (document.hidden) { total += performance.now() - since; since = null; } else since = performance.now();
  });
  return () => Math.round(((total + (since === null ? 0 : performance.now() - since)) / 1000) * 10) / 10;
}

let keymap = null;  // the shortcuts in force (null: none set yet, no listener)

// Keyboard shortcuts: {"a": fn, "ArrowRight": fn, ...}; ignored while typing in a field. A drop-down
// lets go of the keys once a choice is made in it with the mouse (it kept them, and the page's letters
// chose options); one stepped through with the arrow keys keeps them until Tab or Escape. A second call
// replaces the first's keys: a task done keeps only Enter for the next task (the task's own, left on,
// threw on every key once its page was gone).
export function shortcuts(map) {
  const installed = keymap !== null;
  keymap = map;
  if (installed) return;
  let tabbedTo = null, byPointer = false;  // the control Tab moved the focus to (a click moves it elsewhere)
  document.addEventListener("keyup", (ev) => { if (ev.key === "Tab") tabbedTo = document.activeElement; }, true);
  document.addEventListener("pointerdown", () => { tabbedTo = null; byPointer = true; }, true);
  document.addEventListener("keydown", () => { byPointer = false; }, true);
  document.addEventListener("change", (ev) => { if (ev.target.tagName === "SELECT" && byPointer) ev.target.blur(); });
  document.addEventListener("keydown", (ev) => {
    const tag = (ev.target.tagName || "").toLowerCase();  // typing in a field: no shortcuts (a tick box or slider is no field)
    if ((tag === "input" && !["range", "checkbox", "radio"].includes(ev.target.type)) || tag === "textarea" || tag === "select") {
      if (ev.key === "Escape") ev.target.blur();
      return;
    }
    // a button or link reached with Tab keeps its own Enter and Space (the page's Enter submitted instead);
    // one focused by a click leaves Enter to the page, as its help says
    if ((ev.key === "Enter" || ev.key === " ") && tabbedTo === ev.target) return;
    if (ev.ctrlKey || ev.metaKey || ev.altKey) { const f = keymap["Ctrl+" + ev.key]; if (f) { ev.preventDefault(); f(ev); } return; }
    // Caps Lock on: a letter is the one its key gives without it (no shortcut fired: the keys are lower case)
    const caps = ev.key.length === 1 && ev.getModifierState && ev.getModifierState("CapsLock");
    const f = keymap[caps ? (ev.key === ev.key.toUpperCase() ? ev.key.toLowerCase() : ev.key.toUpperCase()) : ev.key];
    if (f) { ev.preventDefault(); f(ev); }
  });
}

export function header(title, clip, task) {
  const h = el("header", {},
    el("a", {href: "/"}, "◀ queue"),
    el("h1", {}, title),
    el("span", {class: "dim"}, clip ? `clip ${clip}` : ""),
    el("span", {class: "grow"}),
    el("span", {id: "progress", class: "dim"}),
    el("span", {id: "who", class: "dim"}));
  document.body.prepend(h);
  return h;
}

let loaded = null, leaving = false;   // the task as loaded (its as_of goes with the answer); an answer saved
// A page brought back by the browser's Back button (its cache) knows old answers: load it again.
window.addEventListener("pageshow", (ev) => { if (ev.persisted) location.reload(); });

// The task and its answered tracks; the item to show: ?track=N, else the first waiting one. A task the
// pipeline has replaced since the link was made is said so at once (its answers would be refused).
// A task that cannot be loaded (a stale link, the app down) or that a rerun withdrew (it asks nothing of
// this kind now) leaves the page with that said, and nothing to submit.
export async function loadTask() {
  await clientChecked;
  const p = params();
  let data;
  if (!p.clip || !p.task) {  // the page's address without its task (it said "no task 'undefined'")
    $("main").replaceChildren(el("div", {id: "load-error", class: "panel", role: "alert"}, el("b", {}, "No task named: "),
      "this page's address names a clip and a task (?clip=…&task=…), as the queue's links do. ", el("a", {href: "/"}, "back to the queue")));
    throw new Error("no clip or task in the address");
  }
  const stop = (what, why) => $("main").replaceChildren(el("div", {id: "load-error", class: "panel", role: "alert"},
    el("b", {}, what), why, " ", el("a", {href: "/"}, "back to the queue")));
  try {
    data = await api(`/api/tasks/${encodeURIComponent(p.clip)}/${encodeURIComponent(p.task)}`);
  } catch (e) {
    stop("This task cannot be loaded: ", e.message);
    throw e;
  }
  if (data.withdrawn) {
    stop("A rerun withdrew this task: ", data.withdrawn);
    throw new Error(`task ${p.task} was withdrawn`);
  }
  const kind = location.pathname.split("/").pop();  // the page's: /annotate/<kind>
  if (data.task.kind !== kind) {
    stop(`This is not a ${kind} task: `, `${p.task} is a ${data.task.kind} task (the queue opens it on its page).`);
    throw new Error(`task ${p.task} is a ${data.task.kind} task`);
  }
  if (kind !== "manual_track" && !(data.task.items || []).length) {
    stop("This task asks nothing: ", "a rerun left it no item to answer.");
    throw new Error(`task ${p.task} has no item`);
  }
  loaded = data;
  if (data.current === false) toast("A rerun replaced this task with a newer one: answers here go to it where they fit. The queue opens the newer task.", "error");
  $("#who").textContent = data.annotator ? `annotator: ${data.annotator}` : "";
  const items = data.task.items || [];
  const waiting = items.filter((it) => !data.answered.includes(it.track_id));
  const free = waiting.filter((it) => !data.held.includes(it.track_id));  // not being done in another tab or browser
  const item = items.find((it) => String(it.track_id) === p.track) || await firstUnclaimed(data.task, free) || waiting[0] || items[0];
  $("#progress").textContent = items.length ? `${items.length - waiting.length} of ${items.length} answered` : "";
  holdItem({clip: data.task.clip, kind: data.task.kind, track_id: item ? item.track_id : -1});
  return {...data, item, waiting, p};
}

// The first of the free items that this tab can claim: another page that read the task as this one
// did (two people on one start-page link) claims the first one in between, and both were given it.
async function firstUnclaimed(task, free) {
  for (const it of free) {
    try {
      if (!(await api("/api/claims", {clip: task.clip, kind: task.kind, track_id: it.track_id})).held_by_other) return it;
    } catch (e) {
      return it;  // the app unreachable: the page's own claim tries again
    }
  }
  return null;
}

const CLAIM_RETRY_MS = 10000;  // a claim that got no answer is tried again this soon (not left unclaimed for the page's life)

// Hold the item shown for this tab while the page is open and its answer not saved (claimed again
// every third of the hold; given back when the page is left or the answer saved: a page left on "Task
// done" held it for good, and a rerun asking about its track again had it skipped for everyone else).
// One another tab or browser holds is said: someone may be doing it.
let releaseHeld = () => {};
async function holdItem(ref) {
  const claim = () => api("/api/claims", ref);
  let holding = true;
  const release = () => fetch("/api/claims/release", {method: "POST", keepalive: true,
    headers: {"Content-Type": "application/json", ...CLIENT_HEADER}, body: JSON.stringify(ref)});
  releaseHeld = () => { if (holding) { holding = false; release(); } };
  // first: a page left before the claim is answered gives it back too (a page restored from the
  // back-forward cache is loaded again, above, and claims again so)
  window.addEventListener("pagehide", () => releaseHeld());
  let said = false, chain = 0;  // one chain of claims at a time: a new client id starts another at once
  const hold = async (mine) => {
    if (!holding || mine !== chain) return;
    let res;
    try {
      res = await claim();
    } catch (e) {
      setTimeout(() => hold(mine), CLAIM_RETRY_MS);  // the app unreachable (restarting, a network blip): claimed again soon
      return;
    }
    if (res.held_by_other && !said) toast(el("span", {id: "held-elsewhere"}, `Another tab or browser opened this item ${Math.round(res.age_s)} s ago: ` +
      "someone may be doing it now (of two answers, the second is refused)."), "warn");
    said = said || res.held_by_other;
    if (holding) setTimeout(() => hold(mine), res.hold_s * 1000 / 3);
    else release();  // the answer was saved while this claim was on its way
  };
  onNewClientId = () => hold(++chain);  // a copied tab's new id claims its item (and hears of the other tab)
  await hold(++chain);
}

// After an answer: the next waiting item of the same task, else wait until the clip's resume has
// run (the server answers ?wait= requests when it ends) and show (and offer with Enter) its next task.
// Warnings (legal but suspicious answers) stay on screen until the person goes on (they vanished with the page).
export async function afterAnswer(clip, taskId, kind, res) {
  leaving = true;
  releaseHeld();  // answered: nobody need be kept from it
  toast(`saved ${res.path}`, "ok");
  const warnings = res.warnings || [];
  for (const w of warnings) toast(w, "warn");
  taskId = res.task_id || taskId;   // a replaced task's answer went to the newer one: go on there
  let data;
  try {
    data = await api(`/api/tasks/${encodeURIComponent(clip)}/${encodeURIComponent(taskId)}`);
  } catch (e) {  // the answer is saved: not said as a failure with Submit on again (pressed, it met a 409 against itself)
    toast(`the answer is saved, but the task cannot be read again (${e.message}): the clip's next item follows`, "warn");
    showWaiting(clip);
    return;
  }
  loaded = {...loaded, as_of: data.as_of};  // answering again from this page edits the person's own answer (no 409)
  const waiting = (data.task.items || []).filter((it) => !data.answered.includes(it.track_id) && !data.held.includes(it.track_id));
  if (waiting.length) {
    const next = `/annotate/${kind}?clip=${encodeURIComponent(clip)}&task=${encodeURIComponent(taskId)}&track=${waiting[0].track_id}`;
    if (!warnings.length) { location.href = next; return; }
    const go = el("button", {id: "next-item", class: "primary", onclick: () => { location.href = next; }}, "Next item (Enter)");
    toast(el("span", {}, `${warnings.length} warning(s) above: the answer is saved. `, go), "warn");
    document.addEventListener("keydown", (ev) => { if (ev.key === "Enter") { ev.stopImmediatePropagation(); go.click(); } }, true);
    go.focus();
    return;
  }
  showWaiting(clip);
}

// Post an answer with what the page saw (the server refuses it, 409, if someone answered the item since).
export function postAnswer(body) {
  return api(`/api/answers?as_of=${encodeURIComponent(loaded ? loaded.as_of : "")}`, body);
}

// Ask before a reload or a link drops work not yet submitted (``dirty()``: the page has some).
export function guardUnsaved(dirty) {
  window.addEventListener("beforeunload", (ev) => { if (!leaving && dirty()) { ev.preventDefault(); ev.returnValue = ""; } });
}

export function showWaiting(clip) {
  const started = performance.now();
  const panel = el("div", {id: "pipeline", class: "panel"}, el("b", {}, "Task done. "), el("span", {id: "pipeline-state"}, "the pipeline resumes the clip…"));
  $("main").replaceChildren(panel);
  shortcuts({});
  const poll = async () => {
    const s = $("#pipeline-state");
    let c;
    try {
      c = await api(`/api/clips/${encodeURIComponent(clip)}?wait=2`);
    } catch (e) {  // the app restarting, the network: say so and ask again
      s.textContent = `cannot reach the app (${e.message}); asking again…`;
      setTimeout(poll, 2000);
      return;
    }
    const busy = c.resume.state === "queued" || c.resume.state === "running";
    if (busy) { s.textContent = `the pipeline is ${c.resume.state} (${Math.round((performance.now() - started) / 1000)} s)…`; poll(); return; }
    const failed = c.resume.failed;  // said first, and not overwritten by what waits (also while Prefect records the run)
    const said = failed ? [el("div", {id: "resume-failed", class: "toast error", role: "alert"}, `The resume failed: ${c.resume.message}`)] : [];
    if (c.next) {
      s.replaceChildren(...said, el("span", {id: "next-ready"}, `next task ready: ${c.next.kind} `), el("a", {href: c.next.url, id: "next-link"}, "open (Enter)"));
      shortcuts({Enter: () => (location.href = c.next.url)});
    } else {
      const why = failed ? "" : `: ${c.resume.message || "done"}`;
      const held = c.tasks.reduce((n, t) => n + t.held_tracks.length, 0);  // waiting, but open in another tab or browser
      s.replaceChildren(...said, el("span", {id: "next-ready"}, held ? `nothing else waits on ${clip}: ${held} item(s) being done in another tab or browser. `
        : `nothing waits for people on ${clip}${why}. `), el("a", {href: "/"}, "back to the queue"));
    }
  };
  poll();
}

// Canvas pixels per pixel on screen: the overlay has the frame's size, shown smaller (a full-HD frame at
// 830 px wide drew 13 px labels 6 px high); lines, labels and dots are sized on screen through it.
export const canvasScale = (canvas) => canvas.width / (canvas.clientWidth || canvas.width);

// Draw boxes (normalised ymin, xmin, ymax, xmax) with labels on a canvas over an image.
export function drawBoxes(canvas, boxes) {
  const ctx = canvas.getContext("2d"), W = canvas.width, H = canvas.height, k = canvasScale(canvas);
  ctx.clearRect(0, 0, W, H);
  ctx.font = `bold ${13 * k}px system-ui`; ctx.lineWidth = 2 * k;
  for (const b of boxes) {
    const [y0, x0, y1, x1] = b.box;
    ctx.strokeStyle = b.color || "#4da3ff"; ctx.setLineDash(b.dash ? [6 * k, 4 * k] : []);
    ctx.strokeRect(x0 * W, y0 * H, (x1 - x0) * W, (y1 - y0) * H);
    if (b.text) {
      const w = ctx.measureText(b.text).width + 8 * k;
      ctx.fillStyle = b.color || "#4da3ff"; ctx.fillRect(x0 * W, Math.max(0, y0 * H - 18 * k), w, 18 * k);
      ctx.fillStyle = "#000"; ctx.fillText(b.text, x0 * W + 4 * k, Math.max(13 * k, y0 * H - 5 * k));
    }
  }
  ctx.setLineDash([]);
}

// The item's images (warehouse-relative paths: its key-frames; CAD selection: the candidates' views too,
// named by ``what``), each loaded once: one gone from the warehouse's
// media is said above the page until it is left (a toast went after 12 s and left broken icons) and
// ``framesNotShown()`` refuses the answer, which would be given on frames nobody saw ("nothing is
// missing", a candidate, an Accept). Resolves to the paths that did not load.
let frameCheck = Promise.resolve([]);
export function checkFrames(paths, what = "key-frame images") {
  const missing = [];
  frameCheck = Promise.all([...new Set(paths)].map((path) => new Promise((done) => {
    const img = new Image();
    img.onload = () => done();
    img.onerror = () => { missing.push(path); done(); };
    img.src = media(path);
  }))).then(() => {
    if (missing.length) $("main").prepend(el("div", {id: "frames-missing", class: "toast error", role: "alert", style: "margin:0 0 10px"},
      `${missing.length} of this item's ${what} cannot be loaded (${missing.sort().join(", ")}): no answer can be given without seeing them.`));
    return missing;
  });
  return frameCheck;
}
// Whether the answer cannot be given (an image of checkFrames did not load: said so); waits for the images
// still loading (an answer sent at once is not refused for that). Pages call it with their Submit off.
export async function framesNotShown() {
  if (!(await frameCheck).length) return false;
  toast("an image of this item cannot be loaded (above): no answer without it", "error");
  return true;
}

// A frame image with an overlay canvas at the image's pixel size (an image that does not load: checkFrames).
export function frameView(src, onload) {
  const img = el("img", {src, alt: "key-frame", draggable: "false"});
  const canvas = el("canvas", {class: "over"});
  const wrap = el("div", {class: "frame"}, img, canvas);
  img.addEventListener("load", () => { canvas.width = img.naturalWidth; canvas.height = img.naturalHeight;
    wrap.style.setProperty("--ar", img.naturalWidth / img.naturalHeight); onload && onload(); });
  return {wrap, img, canvas};
}

// A key-frame's thumbnail in a strip, numbered i + 1: an image that does not load is a dashed
// empty box (checkFrames says which), not its alt text written over the number.
export function thumb(src, i, onclick) {
  const img = el("img", {src, alt: ""});
  const t = el("div", {class: "thumb", title: `key-frame ${i + 1}`, onclick}, img, el("span", {}, i + 1));
  img.addEventListener("error", () => t.classList.add("missing"));
  return t;
}

// Normalised (x, y) of a mouse event over an element.
export function normXY(ev, elem) {
  const r = elem.getBoundingClientRect();
  return [Math.min(1, Math.max(0, (ev.clientX - r.left) / r.width)), Math.min(1, Math.max(0, (ev.clientY - r.top) / r.height))];
}

// The colour of track (or pair) i: its hue steps by the golden angle, never coming back to one
// before, and its lightness cycles over three levels, so that the hues that come close again (8, 13
// and 21 steps on) differ in lightness; the first 20 are told apart. (Eight colours in turn gave
// tracks 0 and 8 one colour.) Light enough for the black text drawn on them.
const LIGHTNESS = [68, 54, 80];
export const trackColor = (i) => `hsl(${Math.round((210 + i * 137.508) % 360)}, 85%, ${LIGHTNESS[i % LIGHTNESS.length]}%)`;
