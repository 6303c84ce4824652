// The session's HTTP API as the viewer uses it: every request carries the session token as a bearer
// header (the token leaves the address bar once the page has loaded).

export class ApiError extends Error {
  constructor(status, detail) {
    super(`${status}: ${detail}`);
    this.status = status;
    this.detail = detail;
  }
}

/** Session id, API base path and token from the page's address: <base>/sessions/<id>/view?token=... */
export function sessionFromLocation(location) {
  const match = location.pathname.match(/^(.*)\/sessions\/([0-9a-f]{32})\/view\/?$/);
  if (!match) throw new Error(`not a session viewer address: ${location.pathname}`);
  const token = new URLSearchParams(location.search).get('token');
  if (!token) throw new Error('the link has no ?token=: open the link `voxfusion stream` printed');
  return { base: match[1], id: match[2], token };
}

export class SessionApi {
  constructor({ base, id, token }) {
    this.id = id;
    this.token = token;
    this.root = `${base}/sessions/${id}`;
    this.wsRoot = `${location.protocol === 'https:' ? 'wss' : 'ws'}://${location.host}${this.root}`;
    this.etags = new Map();
  }

  async request(path, { etagKey = null, accept = 'application/json' } = {}) {
    const headers = { Authorization: `Bearer ${this.token}`, Accept: accept };
    const known = etagKey ? this.etags.get(etagKey) : null;
    if (known) headers['If-None-Match'] = known;
    const response = await fetch(`${this.root}${path}`, { headers, cache: 'no-store' });
    if (response.status === 304) return null;
    if (!response.ok) {
      let detail = response.statusText;
      try { detail = (await response.json()).detail ?? detail; } catch { /* not JSON */ }
      throw new ApiError(response.status, detail);
    }
    if (etagKey && response.headers.get('ETag')) this.etags.set(etagKey, response.headers.get('ETag'));
    return response;
  }

  async json(path) { return (await this.request(path)).json(); }

  status() { return this.json(''); }
  poses() { return this.json('/poses'); }
  latestFrame() { return this.json('/frames/latest'); }
  // The GLB export's frame: its T_world_file maps glTF's Y-up axes to the session's world, which is how
  // the viewer holds the world upright (three.js is Y-up too).
  meshFrame() { return this.json('/mesh/frame?format=glb'); }

  /** The preview mesh (a ~2.5 cm lattice: several times cheaper for the server to extract than the full
   *  one) as PLY bytes and its map version, or null when unchanged since the last call. */
  async mesh() {
    const response = await this.request('/mesh?format=ply&detail=preview',
      { etagKey: 'mesh', accept: 'application/octet-stream' });
    if (!response) return null;
    return { bytes: await response.arrayBuffer(), version: Number(response.headers.get('X-Map-Version')) };
  }

  /** An image route as a blob, or null when unchanged since the last call for the same key. */
  async image(path) {
    const response = await this.request(path, { etagKey: path, accept: 'image/*' });
    return response ? response.blob() : null;
  }

  poseStream() { return new WebSocket(`${this.wsRoot}/poses/stream?token=${encodeURIComponent(this.token)}`); }
}
