// A list of the API's records a page at a time (the API's cursor paging): the first page refreshed as often as the
// page likes, more pages on demand, a text filter over what is loaded, one item selected.

const MAX_LIMIT = 500; // the API's largest page

export class PagedList {
  // fetchPage(limit, cursor) -> {items, next}; entry(item) -> <li> with data-id; matches(item) -> shown or not;
  // onError(err) when the "more" button's page fails.
  constructor({ list, more, fetchPage, entry, matches = () => true, onError = () => {}, pageSize = 50 }) {
    Object.assign(this, { list, moreButton: more, fetchPage, entry, matches, pageSize });
    this.items = [];
    this.next = null;
    this.selected = null;
    this.queue = Promise.resolve(); // one load at a time, in order: a refresh never undoes a later page
    more.hidden = true;
    more.addEventListener("click", () => this.more().catch(onError));
  }

  // The first page again, as long as what is loaded (so that "more" pages stay shown).
  refresh() {
    return this.load(async () => {
      const limit = Math.min(MAX_LIMIT, Math.max(this.pageSize, this.items.length));
      const { items, next } = await this.fetchPage(limit, null);
      this.items = items;
      this.next = next;
    });
  }

  // Forget what is loaded (other filters at the API) and load the first page.
  reset() {
    this.items = [];
    this.next = null;
    return this.refresh();
  }

  more() {
    return this.load(async () => {
      if (!this.next) return;
      const { items, next } = await this.fetchPage(this.pageSize, this.next);
      const known = new Set(this.items.map((item) => item.id));
      this.items.push(...items.filter((item) => !known.has(item.id)));
      this.next = next;
    });
  }

  load(step) {
    this.queue = this.queue.catch(() => {}).then(step).then(() => this.draw());
    return this.queue;
  }

  // Redraw from what is loaded; the number of items shown.
  draw() {
    const shown = this.items.filter(this.matches);
    this.list.replaceChildren(...shown.map((item) => this.entry(item)));
    this.moreButton.hidden = !this.next;
    this.select(this.selected);
    return shown.length;
  }

  select(id) {
    this.selected = id;
    for (const li of this.list.children) li.classList.toggle("selected", li.dataset.id === id);
  }
}
