/** A minimal typed event emitter (works alike in browsers and Node). */
export class Emitter<Events extends { [K in keyof Events]: (...args: never[]) => void }> {
  private readonly handlers = new Map<keyof Events, Set<Events[keyof Events]>>();

  /** Call `fn` on every `type` event; returns a function that removes it. */
  on<K extends keyof Events>(type: K, fn: Events[K]): () => void {
    let set = this.handlers.get(type);
    if (!set) this.handlers.set(type, (set = new Set()));
    set.add(fn);
    return () => this.off(type, fn);
  }

  off<K extends keyof Events>(type: K, fn: Events[K]): void {
    this.handlers.get(type)?.delete(fn);
  }

  /** Resolves with the next `type` event's arguments. */
  once<K extends keyof Events>(type: K): Promise<Parameters<Events[K]>> {
    return new Promise((resolve) => {
      const off = this.on(type, ((...args: Parameters<Events[K]>) => {
        off();
        resolve(args);
      }) as Events[K]);
    });
  }

  protected emit<K extends keyof Events>(type: K, ...args: Parameters<Events[K]>): void {
    const set = this.handlers.get(type);
    if (!set) return;
    for (const fn of [...set]) {
      try {
        (fn as (...a: Parameters<Events[K]>) => void)(...args);
      } catch (err) {
        // A handler's bug must not break the connection's own bookkeeping.
        queueMicrotask(() => {
          throw err;
        });
      }
    }
  }
}
