// Entry of the web page's 3D viewer bundle: the parts of three.js the page uses, bundled and
// minified by deploy/fetch_web_assets.sh into capture/daemon/static/vendor/three-viewer.min.js.
export {
  AmbientLight, Box3, Color, DirectionalLight, GridHelper, Mesh, MeshStandardMaterial,
  PerspectiveCamera, Scene, Vector3, WebGLRenderer, DoubleSide,
} from "three";
export { OrbitControls } from "three/addons/controls/OrbitControls.js";
export { PLYLoader } from "three/addons/loaders/PLYLoader.js";
