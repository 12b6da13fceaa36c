/**
 * Web worker: decodes octree.bin node bytes off the main thread (see decode.ts), plain or
 * octree-coded; the answer carries the decode time in the worker (ms) beside the points.
 */

import { type DecodeParams, decodeNode, transferables } from "./decode";

interface Request {
  id: number;
  buffer: ArrayBuffer;
  count: number;
  params: DecodeParams;
}

const scope = self as unknown as {
  onmessage: ((e: MessageEvent<Request>) => void) | null;
  postMessage(message: unknown, transfer: Transferable[]): void;
};

scope.onmessage = async (e: MessageEvent<Request>) => {
  const { id, buffer, count, params } = e.data;
  try {
    const start = performance.now();
    const points = await decodeNode(buffer, count, params);
    scope.postMessage({ id, points, ms: performance.now() - start }, transferables(points));
  } catch (err) {
    scope.postMessage({ id, error: err instanceof Error ? err.message : String(err) }, []);
  }
};
