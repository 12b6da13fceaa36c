// three.js ships no TypeScript declarations (they are in @types/three, not installed): the
// derivative loader (derivative.ts) uses few of its members and checks what it reads.
declare module "three";
declare module "three/examples/jsm/loaders/GLTFLoader.js";
declare module "three/examples/jsm/loaders/DRACOLoader.js";
