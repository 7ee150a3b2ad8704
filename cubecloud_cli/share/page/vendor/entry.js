// The parts of three.js and Spark that cubecloud's shared page uses, as one global.
import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";

window.CubecloudVendor = { THREE, OrbitControls, SparkRenderer, SplatMesh };
