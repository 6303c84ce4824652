// The live viewer of one session (served at /sessions/<id>/view?token=...). It polls the session's status,
// trajectory, mesh and newest frame, and follows poses on the pose WebSocket; finished sessions show
// their stored map. `document.body.dataset` mirrors what is shown (tests read it).
import './style.css';
import { ApiError, SessionApi, sessionFromLocation } from './api.js';
import { Panel } from './panel.js';
import { SessionScene } from './scene.js';

const STATUS_EVERY_MS = 1000;
const TRAJECTORY_EVERY_MS = 2000;
const MESH_EVERY_MS = 2500;
const MESH_DUTY = 3;  // wait at least 3x as long as the last mesh took: the viewer never keeps the server busy
const ENDED = new Set(['finished', 'failed']);

const panel = new Panel(document);
const view = document.body.dataset;

function start() {
  let session;
  try {
    session = sessionFromLocation(window.location);
  } catch (e) {
    panel.showError(e.message);
    return;
  }
  // Keep the token out of the address bar, history and screenshots; it stays in memory only.
  window.history.replaceState(null, '', window.location.pathname);
  const api = new SessionApi(session);
  const scene = new SessionScene(document.getElementById('scene'));
  panel.setSession(session.id);
  document.getElementById('fit').addEventListener('click', () => {
    scene.userMoved = false;
    scene.fit();
  });
  document.getElementById('follow').addEventListener('change', (e) => {
    scene.follow = e.target.checked;
    if (scene.follow) scene.followCamera();
  });
  document.getElementById('download').addEventListener('click', (e) => downloadMesh(e, api));
  new Viewer(api, scene).run();
}

class Viewer {
  constructor(api, scene) {
    this.api = api;
    this.scene = scene;
    this.status = null;
    this.intrinsics = null;
    this.frameSeq = null;
    this.meshVersion = -1;
    this.lastPose = null;
  }

  run() {
    this.every(STATUS_EVERY_MS, () => this.refreshStatus());
    this.every(TRAJECTORY_EVERY_MS, () => this.refreshTrajectory());
    this.every(MESH_EVERY_MS, () => this.refreshMesh());
    this.followPoses();
  }

  /** Run `task` now and then `ms` after each run ends (never two at once; longer when the task returns a
   *  longer delay, or once the session has ended); errors are shown, not fatal. */
  every(ms, task) {
    const loop = async () => {
      let delay = ms;
      try {
        delay = Math.max(ms, (await task()) || 0);
        panel.showError('');
      } catch (e) {
        if (!(e instanceof ApiError && e.status === 409)) panel.showError(e.message);  // 409: not ready yet
      }
      setTimeout(loop, this.ended() ? delay * 4 : delay);
    };
    loop();
  }

  ended() { return this.status && ENDED.has(this.status.state); }

  async refreshStatus() {
    this.status = await this.api.status();
    view.state = this.status.state;
    view.framesTracked = this.status.frames_tracked;
    panel.setStatus(this.status);
    if (this.status.frames_received > 0) await this.refreshFrame();
  }

  async refreshFrame() {
    const info = await this.api.latestFrame();
    if (info.seq === this.frameSeq) return;
    this.intrinsics = info;
    const depth = await this.api.image('/frames/latest/depth.png');
    if (depth) panel.setImage('depth', depth);
    panel.showColour(info.has_colour);
    if (info.has_colour) {
      const colour = await this.api.image('/frames/latest/colour.jpg');
      if (colour) panel.setImage('colour', colour);
    }
    this.frameSeq = info.seq;  // only once shown: a failed image fetch is retried at the next look
    view.frameSeq = info.seq;
    if (this.lastPose) this.scene.setCamera(this.lastPose.T_world_cam, this.intrinsics);
  }

  async refreshTrajectory() {
    const { poses } = await this.api.poses();
    view.poses = poses.length;
    this.scene.setTrajectory(poses);
    if (poses.length) this.showPose(poses[poses.length - 1]);
  }

  /** Load the mesh when the map changed; returns how long to wait before the next look. */
  async refreshMesh() {
    if (!this.status || this.status.map_version === this.meshVersion) return 0;
    const started = performance.now();
    const mesh = await this.api.mesh();
    const wait = MESH_DUTY * (performance.now() - started);
    if (!mesh) return wait;
    let counts;
    try {
      this.scene.setWorldFrame((await this.api.meshFrame()).T_world_file);
      counts = this.scene.setMesh(mesh.bytes);
    } catch (e) {
      this.api.etags.delete('mesh');  // not shown: fetch it again rather than be told "not modified"
      throw e;
    }
    this.meshVersion = mesh.version;
    view.meshVersion = mesh.version;
    view.meshVertices = counts.vertices;
    panel.setExtra('mesh', `${counts.faces.toLocaleString()} triangles, preview (map v${mesh.version})`);
    return wait;
  }

  showPose(pose) {
    this.lastPose = pose;
    panel.setPose(pose);
    this.scene.setCamera(pose.T_world_cam, null);
  }

  /** Poses as they are tracked; reconnects while the session is open. */
  followPoses() {
    const socket = this.api.poseStream();
    socket.onmessage = (event) => {
      const message = JSON.parse(event.data);
      if (message.event === 'end') return;
      this.showPose(message);
      view.livePoses = Number(view.livePoses || 0) + 1;
    };
    socket.onclose = (event) => {
      if (event.code === 1000 || event.code >= 4400) return;  // session ended, or refused
      setTimeout(() => this.followPoses(), 2000);
    };
  }
}

async function downloadMesh(event, api) {
  event.preventDefault();
  const response = await api.request('/mesh?format=ply', { accept: 'application/octet-stream' });
  const link = document.createElement('a');
  link.href = URL.createObjectURL(await response.blob());
  link.download = `voxfusion-${api.id.slice(0, 8)}.ply`;
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 10000);
}

start();
