// The side panel: session state and counters, the current pose, the newest depth / colour frame.

const COUNTERS = [
  ['frames_received', 'received'], ['frames_tracked', 'tracked'], ['frames_lost', 'lost'],
  ['frames_limited', 'limited'], ['frames_dropped', 'dropped'], ['keyframes', 'keyframes'], ['voxels', 'voxels'],
  ['fps', 'tracking fps', (v) => v.toFixed(1)], ['latency_ms', 'latency', (v) => (v == null ? '–' : `${v.toFixed(0)} ms`)],
  ['map_version', 'map version'],
];

export class Panel {
  constructor(doc) {
    this.doc = doc;
    this.counters = doc.getElementById('counters');
    this.state = doc.getElementById('state');
    this.pose = doc.getElementById('pose');
    this.error = doc.getElementById('error');
    this.images = { depth: doc.getElementById('depth'), colour: doc.getElementById('colour') };
    this.extra = new Map();
  }

  setSession(id) { this.doc.getElementById('session-id').textContent = id; }

  setStatus(status) {
    this.state.textContent = status.state + (status.last_error ? `: ${status.last_error}` : '');
    this.state.className = `state ${status.state}`;
    const rows = COUNTERS.map(([key, label, fmt]) => [label, fmt ? fmt(status[key]) : String(status[key] ?? 0)]);
    for (const [label, value] of this.extra) rows.push([label, value]);
    this.counters.replaceChildren(...rows.map(([label, value]) => {
      const tr = this.doc.createElement('tr');
      const th = this.doc.createElement('th');
      const td = this.doc.createElement('td');
      th.textContent = label;
      td.textContent = value;
      tr.append(th, td);
      return tr;
    }));
  }

  /** An extra counter row shown after the session's own (e.g. the mesh's size). */
  setExtra(label, value) { this.extra.set(label, value); }

  setPose(pose) {
    const T = pose.T_world_cam;
    const position = [T[0][3], T[1][3], T[2][3]].map((v) => v.toFixed(3)).join(', ');
    const state = pose.tracking_state ?? (pose.lost ? 'lost' : 'normal');  // older servers send only `lost`
    this.pose.textContent = `frame ${pose.seq}${state === 'normal' ? '' : ` (${state})`}\nposition [${position}] m`;
  }

  setImage(kind, blob) {
    const img = this.images[kind];
    const old = img.src;
    img.src = URL.createObjectURL(blob);
    if (old.startsWith('blob:')) URL.revokeObjectURL(old);
  }

  /** Show the colour view only while the newest frame has colour (3D Scanner App: every third frame). */
  showColour(shown) { this.doc.getElementById('colour-figure').hidden = !shown; }

  showError(message) { this.error.textContent = message || ''; }
}
