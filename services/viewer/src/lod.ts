/**
 * Level-of-detail selection: which octree nodes to draw and which to load next.
 *
 * Nodes are visited largest projected size first (bounding-sphere radius in pixels) until
 * the point budget is spent; a node is drawn when loaded, otherwise queued for loading in
 * that same priority order. Children are only considered below a drawn node, so the cut
 * through the octree deepens progressively as data arrives.
 */

import type { TileNode } from "./potree";

export interface ViewInfo {
  /** Column-major world-to-clip matrix for the local frame (16 numbers). */
  viewProj: ArrayLike<number>;
  /** Camera position in the local frame. */
  eye: [number, number, number];
  /** Viewport focal length in pixels: (height / 2) / tan(fovY / 2). */
  focalPx: number;
}

export interface Selection {
  visible: TileNode[];
  toLoad: TileNode[];
  numPoints: number;
  /** Nodes in `visible` that have children not drawn this frame (their points stand in for them). */
  coarse: Set<TileNode>;
}

type Plane = [number, number, number, number];

/** Frustum planes (a, b, c, d with ax + by + cz + d >= 0 inside) of a column-major clip matrix. */
export function frustumPlanes(m: ArrayLike<number>): Plane[] {
  const row = (r: number): [number, number, number, number] => [m[r], m[4 + r], m[8 + r], m[12 + r]];
  const r0 = row(0);
  const r1 = row(1);
  const r2 = row(2);
  const r3 = row(3);
  const planes: Plane[] = [];
  for (const [a, s] of [[r0, 1], [r0, -1], [r1, 1], [r1, -1], [r2, 1], [r2, -1]] as [number[], number][]) {
    const p: Plane = [r3[0] + s * a[0], r3[1] + s * a[1], r3[2] + s * a[2], r3[3] + s * a[3]];
    const n = Math.hypot(p[0], p[1], p[2]) || 1;
    planes.push([p[0] / n, p[1] / n, p[2] / n, p[3] / n]);
  }
  return planes;
}

/** Whether an axis-aligned box is at least partly inside all planes. */
export function boxInFrustum(planes: Plane[], min: number[], max: number[]): boolean {
  for (const p of planes) {
    // The box corner farthest along the plane normal decides.
    const x = p[0] >= 0 ? max[0] : min[0];
    const y = p[1] >= 0 ? max[1] : min[1];
    const z = p[2] >= 0 ? max[2] : min[2];
    if (p[0] * x + p[1] * y + p[2] * z + p[3] < 0) return false;
  }
  return true;
}

/** Projected bounding-sphere radius of a node in pixels (huge when the eye is inside it). */
export function projectedRadius(node: TileNode, view: ViewInfo): number {
  const c = node.center();
  const r = node.radius();
  const d = Math.hypot(c[0] - view.eye[0], c[1] - view.eye[1], c[2] - view.eye[2]);
  if (d <= r) return Number.MAX_VALUE;
  return (view.focalPx * r) / Math.sqrt(d * d - r * r);
}

class MaxHeap<T> {
  private items: { value: T; key: number }[] = [];

  get size(): number {
    return this.items.length;
  }

  push(value: T, key: number): void {
    const items = this.items;
    items.push({ value, key });
    let i = items.length - 1;
    while (i > 0) {
      const parent = (i - 1) >> 1;
      if (items[parent].key >= items[i].key) break;
      [items[parent], items[i]] = [items[i], items[parent]];
      i = parent;
    }
  }

  pop(): T | undefined {
    const items = this.items;
    if (items.length === 0) return undefined;
    const top = items[0];
    const last = items.pop()!;
    if (items.length > 0) {
      items[0] = last;
      let i = 0;
      for (;;) {
        const l = 2 * i + 1;
        const r = l + 1;
        let best = i;
        if (l < items.length && items[l].key > items[best].key) best = l;
        if (r < items.length && items[r].key > items[best].key) best = r;
        if (best === i) break;
        [items[best], items[i]] = [items[i], items[best]];
        i = best;
      }
    }
    return top.value;
  }
}

/**
 * Choose nodes to draw under `budget` points.
 *
 * `minNodePx`: children whose projected radius is below this many pixels are not refined into.
 */
export function selectNodes(root: TileNode, view: ViewInfo, budget: number, minNodePx: number): Selection {
  const planes = frustumPlanes(view.viewProj);
  const heap = new MaxHeap<TileNode>();
  const visible: TileNode[] = [];
  const toLoad: TileNode[] = [];
  const drawn = new Set<TileNode>();
  let numPoints = 0;
  heap.push(root, Number.MAX_VALUE);
  while (heap.size > 0) {
    const node = heap.pop()!;
    if (!boxInFrustum(planes, node.min, node.max)) continue;
    // The root is drawn whatever the budget, so that a budget below its size still shows the scan.
    if (numPoints + node.numPoints > budget && node !== root) break;
    if (node.state !== "loaded") {
      if (node.state === "unloaded") toLoad.push(node);
      continue;
    }
    visible.push(node);
    drawn.add(node);
    numPoints += node.numPoints;
    for (const child of node.children) {
      if (!child) continue;
      const px = projectedRadius(child, view);
      if (px < minNodePx) continue;
      heap.push(child, px);
    }
  }
  const coarse = new Set<TileNode>();
  for (const node of visible) {
    if (node.children.some((c) => c !== null && !drawn.has(c))) coarse.add(node);
  }
  return { visible, toLoad, numPoints, coarse };
}
