// IWER (Meta's WebXR emulator) as a Meta Quest 3 in place of the browser's WebXR: run it
// before the page's own scripts (the browser tests inject dist/emulate.js so). The
// emulated device is window.posecastEmulator (move it: .position, .quaternion,
// .controllers.left / .right); window.posecastEmulatorConfig is the device's config.
import { XRDevice, metaQuest3 } from "iwer";

const device = new XRDevice(metaQuest3);
// Headless Chromium has a native navigator.xr that wants a user gesture: replace it.
device.installRuntime({ forceInstall: true });
window.posecastEmulator = device;
window.posecastEmulatorConfig = metaQuest3;
