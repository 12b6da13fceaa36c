/** Web worker: decodes octree.bin node bytes off the main thread (see decode.ts). */

import { type DecodeParams, decodePoints, transferables } from "./decode";

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

scope.onmessage = (e: MessageEvent<Request>) => {
  const { id, buffer, count, params } = e.data;
  try {
    const points = decodePoints(buffer, count, params);
    scope.postMessage({ id, points }, transferables(points));
  } catch (err) {
    scope.postMessage({ id, error: err instanceof Error ? err.message : String(err) }, []);
  }
};
