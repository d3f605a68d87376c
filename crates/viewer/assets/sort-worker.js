// Depth sort of the Gaussians: exact back-to-front order by view depth.
// Runs as a module worker; the page imports sortBackToFront as a fallback.

// Sorts the Gaussians whose view depth z = r . mean + t exceeds 0.01 from far to near.
// Ties keep the reverse of index order, so front to back the order is stable.
// means: Float32Array of 3n; row: [r0, r1, r2, t]; out: Uint32Array of at least n.
// Returns the number of indices written to out.
export function sortBackToFront(means, n, row, out, scratch) {
  const s = scratch.n === n ? scratch : resize(scratch, n);
  const depth = s.depth;
  const bits = s.bits;
  const a = s.a;
  const b = s.b;
  const [r0, r1, r2, t] = row;
  let m = 0;
  for (let i = 0, k = 0; i < n; i++, k += 3) {
    const z = r0 * means[k] + r1 * means[k + 1] + r2 * means[k + 2] + t;
    depth[i] = z;
    // Same test as the renderer, in single precision.
    if (depth[i] > 0.01) a[m++] = i;
  }
  // Positive floats order as their bit patterns: two 16-bit counting-sort passes.
  const counts = s.counts;
  counts.fill(0);
  for (let j = 0; j < m; j++) counts[bits[a[j]] & 0xffff]++;
  prefix(counts);
  for (let j = 0; j < m; j++) {
    const i = a[j];
    b[counts[bits[i] & 0xffff]++] = i;
  }
  counts.fill(0);
  for (let j = 0; j < m; j++) counts[bits[b[j]] >>> 16]++;
  prefix(counts);
  // Near to far into a, then reversed into out.
  for (let j = 0; j < m; j++) {
    const i = b[j];
    a[counts[bits[i] >>> 16]++] = i;
  }
  for (let j = 0; j < m; j++) out[j] = a[m - 1 - j];
  return m;
}

function prefix(counts) {
  let sum = 0;
  for (let k = 0; k < 65536; k++) {
    const c = counts[k];
    counts[k] = sum;
    sum += c;
  }
}

function resize(scratch, n) {
  scratch.n = n;
  scratch.depth = new Float32Array(n);
  scratch.bits = new Uint32Array(scratch.depth.buffer);
  scratch.a = new Uint32Array(n);
  scratch.b = new Uint32Array(n);
  scratch.counts = scratch.counts || new Uint32Array(65536);
  return scratch;
}

export function newScratch() {
  return { n: -1 };
}

// Worker side: {type: "scene", means, n, gen} then {type: "sort", row, gen, seq, buffer?}.
const inWorker =
  typeof WorkerGlobalScope !== "undefined" && self instanceof WorkerGlobalScope;
if (inWorker) {
  let means = null;
  let n = 0;
  let gen = -1;
  const scratch = newScratch();
  self.onmessage = (e) => {
    const msg = e.data;
    if (msg.type === "scene") {
      means = msg.means;
      n = msg.n;
      gen = msg.gen;
    } else if (msg.type === "sort") {
      if (msg.gen !== gen || !means) return;
      const t0 = performance.now();
      let out = msg.buffer ? new Uint32Array(msg.buffer) : null;
      if (!out || out.length < n) out = new Uint32Array(Math.max(n, 1));
      const count = sortBackToFront(means, n, msg.row, out, scratch);
      const ms = performance.now() - t0;
      self.postMessage(
        { type: "sorted", gen, seq: msg.seq, count, ms, indices: out },
        [out.buffer],
      );
    }
  };
}
