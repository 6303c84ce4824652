// The 3D view: the session's world (mesh, trajectory, current camera frustum) held upright in three.js's
// Y-up axes, with orbit controls. All session data is in world coordinates (metres, OpenCV camera axes
// for poses); `worldGroup` carries the world -> display transform.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { PLYLoader } from 'three/addons/loaders/PLYLoader.js';

const FRUSTUM_DEPTH_M = 0.3;

export class SessionScene {
  constructor(container) {
    this.container = container;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
    container.appendChild(this.renderer.domElement);

    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0x1b1e24);
    this.camera = new THREE.PerspectiveCamera(60, 1, 0.02, 200);
    this.camera.position.set(2, 2, 2);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = true;
    // The view follows the growing scan (re-fitted with each mesh) until the user moves it.
    this.userMoved = false;
    this.controls.addEventListener('start', () => { this.userMoved = true; });

    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x444450, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.2);
    sun.position.set(3, 6, 2);
    this.scene.add(sun);
    this.grid = new THREE.GridHelper(20, 40, 0x3a4150, 0x2a2f38);
    this.scene.add(this.grid);

    this.worldGroup = new THREE.Group();
    this.worldGroup.matrixAutoUpdate = false;
    this.scene.add(this.worldGroup);

    this.mesh = null;
    this.trajectory = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: 0xffa630 }));
    this.trajectory.frustumCulled = false;
    this.worldGroup.add(this.trajectory);
    this.lostPoints = new THREE.Points(new THREE.BufferGeometry(),
      new THREE.PointsMaterial({ color: 0xff3b3b, size: 6, sizeAttenuation: false }));
    this.lostPoints.frustumCulled = false;
    this.worldGroup.add(this.lostPoints);
    this.frustum = new THREE.LineSegments(new THREE.BufferGeometry(),
      new THREE.LineBasicMaterial({ color: 0x4fd1ff }));
    this.frustum.matrixAutoUpdate = false;
    this.frustum.visible = false;
    this.worldGroup.add(this.frustum);

    this.follow = false;
    this.loader = new PLYLoader();
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
    this.renderer.setAnimationLoop(() => this.draw());
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.container;
    if (!w || !h) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
  }

  /** World -> display: `T_world_file` of the GLB export (display = glTF Y-up), inverted. */
  setWorldFrame(T_world_file) {
    const m = rowMajor(T_world_file);
    this.worldGroup.matrix.copy(m.invert());
    this.worldGroup.matrixWorldNeedsUpdate = true;
  }

  /** Replace the mesh with a PLY (world coordinates, vertex colours when present). Returns its counts. */
  setMesh(plyBytes) {
    const geometry = this.loader.parse(plyBytes);
    if (!geometry.getAttribute('normal')) geometry.computeVertexNormals();
    const hasColour = Boolean(geometry.getAttribute('color'));
    // Front faces only: the mesh's triangles face the free space the cameras saw, so from outside a room
    // the near walls fall away and the inside shows (a "dollhouse" view).
    const material = new THREE.MeshLambertMaterial({
      vertexColors: hasColour, color: hasColour ? 0xffffff : 0xb8c4d6, side: THREE.FrontSide });
    const mesh = new THREE.Mesh(geometry, material);
    if (this.mesh) {
      this.worldGroup.remove(this.mesh);
      this.mesh.geometry.dispose();
      this.mesh.material.dispose();
    }
    this.mesh = mesh;
    this.worldGroup.add(mesh);
    if (!this.userMoved && !this.follow) this.fit();
    const index = geometry.getIndex();
    return { vertices: geometry.getAttribute('position').count, faces: index ? index.count / 3 : 0 };
  }

  /** Trajectory through the camera centres of `poses` ([{T_world_cam, lost}], tracking order). */
  setTrajectory(poses) {
    const centres = poses.map((p) => [p.T_world_cam[0][3], p.T_world_cam[1][3], p.T_world_cam[2][3]]);
    this.trajectory.geometry.dispose();
    this.trajectory.geometry = new THREE.BufferGeometry().setAttribute(
      'position', new THREE.Float32BufferAttribute(centres.flat(), 3));
    const lost = poses.filter((p) => p.lost).map((p) => [p.T_world_cam[0][3], p.T_world_cam[1][3], p.T_world_cam[2][3]]);
    this.lostPoints.geometry.dispose();
    this.lostPoints.geometry = new THREE.BufferGeometry().setAttribute(
      'position', new THREE.Float32BufferAttribute(lost.flat(), 3));
    if (!this.userMoved && !this.follow && !this.mesh && centres.length > 1) this.fit();
  }

  /** The current camera: a frustum from the newest frame's intrinsics at `T_world_cam` (OpenCV axes). */
  setCamera(T_world_cam, intrinsics) {
    if (intrinsics) {
      this.frustum.geometry.dispose();
      this.frustum.geometry = frustumGeometry(intrinsics, FRUSTUM_DEPTH_M);
    }
    this.frustum.matrix.copy(rowMajor(T_world_cam));
    this.frustum.matrixWorldNeedsUpdate = true;
    this.frustum.visible = true;
    if (this.follow) this.followCamera();
  }

  followCamera() {
    this.worldGroup.updateMatrixWorld(true);
    const camToDisplay = this.frustum.matrixWorld;
    const eye = new THREE.Vector3(0, -0.3, -1.0).applyMatrix4(camToDisplay);  // behind and above the camera
    const target = new THREE.Vector3(0, 0, 1.5).applyMatrix4(camToDisplay);
    this.camera.position.copy(eye);
    this.controls.target.copy(target);
  }

  /** Frame everything there is (the mesh, else the trajectory) from above and to the side. */
  fit() {
    this.worldGroup.updateMatrixWorld(true);
    const box = new THREE.Box3();
    if (this.mesh) box.expandByObject(this.mesh);
    else box.expandByObject(this.trajectory);
    if (box.isEmpty()) return;
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    const radius = Math.max(sphere.radius, 0.5);
    const direction = new THREE.Vector3(0.5, 1.0, 0.8).normalize();  // behind the first camera, 45 deg up
    this.camera.position.copy(sphere.center).addScaledVector(direction, radius * 1.9);
    this.controls.target.copy(sphere.center);
    this.grid.position.y = box.min.y;
  }

  draw() {
    this.controls.update();
    this.renderer.render(this.scene, this.camera);
  }
}

function rowMajor(rows) {
  const m = new THREE.Matrix4();
  m.set(...rows[0], ...rows[1], ...rows[2], ...rows[3]);
  return m;
}

function frustumGeometry({ width, height, fx, fy, cx, cy }, depth) {
  const corner = (u, v) => [(u - cx) / fx * depth, (v - cy) / fy * depth, depth];
  const c = [corner(0, 0), corner(width, 0), corner(width, height), corner(0, height)];
  const o = [0, 0, 0];
  const up = [(width / 2 - cx) / fx * depth, (-0.15 * height - cy) / fy * depth, depth];  // marks image "up"
  const segments = [o, c[0], o, c[1], o, c[2], o, c[3], c[0], c[1], c[1], c[2], c[2], c[3], c[3], c[0],
    c[0], up, up, c[1]];
  return new THREE.BufferGeometry().setAttribute('position', new THREE.Float32BufferAttribute(segments.flat(), 3));
}
