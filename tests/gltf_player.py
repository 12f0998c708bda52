"""A three.js page that plays a GLB's clips and reads back the vertices it shows, for the tests that check our files
(and the USD made from an avatar) against an independent glTF player: serve it with `browser.serve_folder(root,
PAGE, NODE_MODULES)` and call `play`."""

import json
from pathlib import Path

import numpy as np

PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>bone asset check</title><link rel="icon" href="data:,">
<script type="importmap">
{"imports": {"three": "/node_modules/three/build/three.module.js",
             "three/addons/": "/node_modules/three/examples/jsm/"}}
</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

// Load `url`, play the clips named `clips` together and read, at each of `times`, the vertices three.js shows of
// the mesh of each node in `wanted` ({node index: vertex ids}): skinned (getVertexPosition) or placed by its node.
window.play = async (url, clips, times, wanted) => {
  const gltf = await new GLTFLoader().loadAsync(url);
  const meshes = {};
  gltf.scene.traverse((o) => {
    const found = gltf.parser.associations.get(o);
    if (o.isMesh && found && found.nodes !== undefined) meshes[found.nodes] = o;
  });
  const mixer = new THREE.AnimationMixer(gltf.scene);
  const actions = clips.map((n) => mixer.clipAction(THREE.AnimationClip.findByName(gltf.animations, n)));
  const out = {};
  for (const name of Object.keys(wanted)) out[name] = [];
  const v = new THREE.Vector3();
  for (const t of times) {
    for (const a of actions) { a.reset(); a.setLoop(THREE.LoopOnce, 1); a.clampWhenFinished = true; a.play(); }
    mixer.setTime(t);
    gltf.scene.updateMatrixWorld(true);
    for (const [name, ids] of Object.entries(wanted)) {
      const mesh = meshes[name];
      out[name].push(ids.map((i) => {
        mesh.getVertexPosition(i, v);
        if (!mesh.isSkinnedMesh) v.applyMatrix4(mesh.matrixWorld);
        return [v.x, v.y, v.z];
      }));
    }
  }
  return {meshes: Object.keys(meshes).map(Number),
          skinned: Object.keys(meshes).filter((k) => meshes[k].isSkinnedMesh).map(Number),
          clips: gltf.animations.map((c) => c.name), positions: out};
};
</script></head><body></body></html>
"""


def play(browser, served, path: Path, clips: list[str], times: list[float], wanted: dict) -> dict:
    """Play `path` (copied into the served folder) in three.js: the clips named `clips` together, and at each of
    `times` the vertices of the mesh of each node in `wanted` ({node index: vertex ids}); positions come back as
    arrays (times, ids, 3) by node."""
    root, base = served
    (root / path.name).write_bytes(path.read_bytes())
    state = browser.load(f"{base}/index.html")
    assert state["errors"] == [], state
    call = f"window.play({json.dumps('/' + path.name)}, {json.dumps(clips)}, {json.dumps(times)}, {json.dumps(wanted)})"
    result = browser.send("Runtime.evaluate", {"expression": call, "awaitPromise": True, "returnByValue": True})
    assert "exceptionDetails" not in result, result["exceptionDetails"]
    got = result["result"]["value"]
    got["positions"] = {k: np.array(v) for k, v in got["positions"].items()}
    return got
