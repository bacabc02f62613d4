/** posecast: the client SDK of the posecast relay (browsers and Node 20+). */
export { PosecastClient, checkPose } from "./client.js";
export type { ClientOptions, ClientEvents, Codec } from "./client.js";
export { ClockEstimator, pongOffset, pongRoundTrip, monotonicSeconds } from "./clock.js";
export { StreamBuffer, PlayoutDelay, RoomPlayoutDelay, percentile, DEFAULT_BUFFER_CAPACITY } from "./buffers.js";
export type { Bracket, Velocity } from "./buffers.js";
export { soa, dqSlerp, motorLerp, interpolator, hemisphereSign, INTERPOLATORS } from "./interp.js";
export type { Interpolator, MethodName } from "./interp.js";
export { Receiver } from "./receiver.js";
export type { Peer, SharedObject, RemoteStream, RenderedPose, RenderFrame } from "./receiver.js";
export {
  decodeMessage,
  encodeControl,
  encodeUpdate,
  encodeSnapshot,
  float16,
  toFloat16,
  DEFAULT_VOLUME,
  PROTOCOL_VERSION,
  ROOM_USER,
  SCHEMAS,
} from "./messages.js";
export type * from "./messages.js";
export {
  PosecastError,
  ServerError,
  JoinRefused,
  DecodeError,
  ConnectionClosed,
  UsageError,
  ERROR_CODES,
} from "./errors.js";
export { Link, defaultWebSocket } from "./link.js";
export type { WebSocketLike } from "./link.js";
export {
  CompactSession,
  CODEC_FRAME_BYTE,
  Volume,
  poseCodes,
  codesToPose,
  codesValid,
  predict,
  encodeUpdateFrame,
  decodeUpdateFrame,
  decodeSnapshotFrame,
  crc32,
  roundHalfEven,
} from "./compact.js";
export type { CompactEntry, CompactFrame, CompactHeader, Baselines } from "./compact.js";
export { XRPublisher, xrPose, inVolume } from "./webxr.js";
export type { XRPublisherOptions } from "./webxr.js";
